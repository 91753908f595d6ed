"""TaCompareString: true iff ``str_a`` equals ``str_b``."""

from temoto import Action


class TaCompareString(Action):
    blocking = False  # never waits: runs inline, on the thread evolving the graph

    def on_run(self) -> bool:
        return self.inputs.get_string("str_a") == self.inputs.get_string("str_b")
