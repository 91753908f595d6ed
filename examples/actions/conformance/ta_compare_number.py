"""TaCompareNumber: compares ``num_a`` with ``num_b`` by ``operation``; unknown ones fail."""

import operator

from temoto import Action

_OPERATORS = {
    "==": operator.eq,
    "!=": operator.ne,
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
}


class TaCompareNumber(Action):
    blocking = False  # never waits: runs inline, on the thread evolving the graph

    def on_run(self) -> bool:
        op = self.inputs.get_string("operation")
        if op not in _OPERATORS:
            raise ValueError(f"unknown operation {op!r} (expected one of {', '.join(_OPERATORS)})")
        return bool(
            _OPERATORS[op](self.inputs.get_number("num_a"), self.inputs.get_number("num_b"))
        )
