"""TaTriggerResultMulti (spontaneous): produces ``results`` one per run, ``delay`` s apart.

Run k (k < len(results)) sleeps ``delay`` seconds, then yields results[k] like TaTriggerResult.
Once every result was produced, the next run blocks until it is stopped and returns true.
"""

from temoto import Action


class TaTriggerResultMulti(Action):
    def __init__(self) -> None:
        super().__init__()
        self.index = 0

    def on_run(self) -> bool:
        results = self.inputs.get_strings("results")
        if self.index >= len(results):
            self.wait_until_stopped()
            return True
        self.sleep(self.inputs.get_number("delay"))
        result = results[self.index]
        self.index += 1
        if result == "on_true":
            return True
        if result == "on_false":
            return False
        raise RuntimeError(f"triggered error (result {result!r})")
