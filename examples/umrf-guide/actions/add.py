"""Add: ``sum = a + b``."""

from temoto import Action


class Add(Action):
    def on_run(self) -> bool:
        self.outputs["sum"] = self.inputs.get_number("a") + self.inputs.get_number("b")
        return True
