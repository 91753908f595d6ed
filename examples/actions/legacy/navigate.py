"""Navigate: a stand-in for navigation in the GPT parser's structure-only examples (1 s)."""

from temoto import Action


class Navigate(Action):
    def on_run(self) -> bool:
        self.log("navigating")
        self.sleep(1.0)
        return True
