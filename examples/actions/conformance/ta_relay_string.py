"""TaRelayString: ``string_out`` = ``string_in``."""

from temoto import Action


class TaRelayString(Action):
    blocking = False  # never waits: runs inline, on the thread evolving the graph

    def on_run(self) -> bool:
        self.outputs["string_out"] = self.inputs.get_string("string_in")
        return True
