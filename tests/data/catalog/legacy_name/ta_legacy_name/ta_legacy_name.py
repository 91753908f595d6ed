"""TaLegacyName (catalog test fixture): described by a file named plain ``umrf.json``."""

from temoto import Action


class TaLegacyName(Action):
    def on_run(self) -> bool:
        return True
