"""Timer: a stand-in for the GPT parser examples' wait step (1 s)."""

from temoto import Action


class Timer(Action):
    def on_run(self) -> bool:
        self.sleep(1.0)
        return True
