"""TaIngestResult: counts its runs (the instance lives across runs).

The first run reads ``ingest_count`` and ``timeout``. Every run increments the counter; once it
reaches ``ingest_count`` the run returns true at once, otherwise it waits up to ``timeout``
seconds: false on timeout, true if it is stopped meanwhile.
"""

from temoto import Action


class TaIngestResult(Action):
    def __init__(self) -> None:
        super().__init__()
        self.count = 0
        self.ingest_count = 0.0
        self.timeout = 0.0

    def on_run(self) -> bool:
        if self.count == 0:
            self.ingest_count = self.inputs.get_number("ingest_count")
            self.timeout = self.inputs.get_number("timeout")
        self.count += 1
        self.log(f"ingested result {self.count}")
        if self.count >= self.ingest_count:
            return True
        return self.wait_until_stopped(self.timeout)
