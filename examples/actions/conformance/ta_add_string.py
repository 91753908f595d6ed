"""TaAddString: ``result`` = ``str_a`` + " and " + ``str_b``."""

from temoto import Action


class TaAddString(Action):
    blocking = False  # never waits: runs inline, on the thread evolving the graph

    def on_run(self) -> bool:
        self.outputs["result"] = (
            f"{self.inputs.get_string('str_a')} and {self.inputs.get_string('str_b')}"
        )
        return True
