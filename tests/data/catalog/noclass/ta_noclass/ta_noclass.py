"""Imports fine but defines no TaNoclass (catalog test fixture)."""

from temoto import Action


class SomethingElse(Action):
    def on_run(self) -> bool:
        return True


TaNoclass = 42  # not an Action subclass
