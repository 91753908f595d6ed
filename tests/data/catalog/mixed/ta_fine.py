"""TaFine (catalog test fixture): indexed beside two broken descriptions."""

from temoto import Action


class TaFine(Action):
    def on_run(self) -> bool:
        return True
