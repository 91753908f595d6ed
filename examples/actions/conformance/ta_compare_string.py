"""TaCompareString: true iff ``str_a`` equals ``str_b``."""

from temoto import Action


class TaCompareString(Action):
    def on_run(self) -> bool:
        return self.inputs.get_string("str_a") == self.inputs.get_string("str_b")
