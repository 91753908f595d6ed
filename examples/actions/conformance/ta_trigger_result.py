"""TaTriggerResult: ``result`` "on_true" → true, "on_false" → false, anything else raises."""

from temoto import Action


class TaTriggerResult(Action):
    blocking = False  # never waits: runs inline, on the thread evolving the graph

    def on_run(self) -> bool:
        result = self.inputs.get_string("result")
        if result == "on_true":
            return True
        if result == "on_false":
            return False
        raise RuntimeError(f"triggered error (result {result!r})")
