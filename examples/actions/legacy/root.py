"""Root: the start marker of graphs made by the GPT UMRF parser; does nothing."""

from temoto import Action


class Root(Action):
    def on_run(self) -> bool:
        return True
