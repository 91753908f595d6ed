"""TaGood: text_out = text + "!" (catalog test fixture)."""

from temoto import Action


class TaGood(Action):
    def on_run(self) -> bool:
        self.outputs["text_out"] = self.inputs.get_string("text") + "!"
        return True
