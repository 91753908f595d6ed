"""Divide: ``quotient = a / b``. Dividing by 0 raises, which makes the node's result
``on_error``; ``temoto -v run`` prints where (this file, the line below)."""

from temoto import Action


def _divide(a: float, b: float) -> float:
    return a / b  # ZeroDivisionError when b is 0


class Divide(Action):
    blocking = False  # never waits: runs inline, on the thread evolving the graph

    def on_run(self) -> bool:
        self.outputs["quotient"] = _divide(self.inputs.get_number("a"), self.inputs.get_number("b"))
        return True
