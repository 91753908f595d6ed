"""TaLogger: writes every string of ``messages`` to the action log."""

from temoto import Action


class TaLogger(Action):
    def on_run(self) -> bool:
        for message in self.inputs.get_strings("messages"):
            self.log(message)
        return True
