"""TaTwin (catalog test fixture): offered by two folders."""

from temoto import Action


class TaTwin(Action):
    def on_run(self) -> bool:
        return True
