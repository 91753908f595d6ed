"""Say: write ``text`` to the action's log and pass it on as ``said``."""

from temoto import Action


class Say(Action):
    blocking = False  # never waits: runs inline, on the thread evolving the graph

    def on_run(self) -> bool:
        text = self.inputs.get_string("text")
        self.log(text)
        self.outputs["said"] = text
        return True
