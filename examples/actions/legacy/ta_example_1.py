"""TaExample1: passes ``distance`` on with one more unit, after one second."""

from temoto import Action


class TaExample1(Action):
    def on_run(self) -> bool:
        amount = self.inputs.get_number("distance::amount")
        unit = self.inputs.get_string("distance::unit")
        self.log(f"{amount:g} {unit}")
        self.sleep(1.0)
        self.outputs["distance::amount"] = amount + 1
        self.outputs["distance::unit"] = unit
        return True
