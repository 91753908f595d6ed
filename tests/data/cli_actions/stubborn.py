"""Stubborn: ignores its stop request (blocks in real time for ``seconds``), as a plugin with
a blocking call does; for the tests of ``--stop-timeout``."""

import time

from temoto import Action


class Stubborn(Action):
    def on_run(self) -> bool:
        time.sleep(self.inputs.get_number("seconds"))
        return True
