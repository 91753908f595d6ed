"""TaLogger: writes every string of ``messages`` to the action log."""

from temoto import Action


class TaLogger(Action):
    blocking = False  # never waits: runs inline, on the thread evolving the graph

    def on_run(self) -> bool:
        for message in self.inputs.get_strings("messages"):
            self.log(message)
        return True
