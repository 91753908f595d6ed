"""Root: the start marker of graphs made by the GPT UMRF parser; does nothing."""

from temoto import Action


class Root(Action):
    blocking = False  # never waits: runs inline, on the thread evolving the graph

    def on_run(self) -> bool:
        return True
