"""Resource managers: servers on the Resource Registrar for one kind of resource each.

* :mod:`temoto.managers.process`: operating-system processes (:class:`ProcessManager`, the
  ``"process"`` server); :mod:`temoto.managers.process_client`: :class:`ProcessManagerClient`
  for consumers.
"""

from __future__ import annotations

from temoto.managers.process import ProcessManager, ProcessRequest, ProcessResponse
from temoto.managers.process_client import FailurePolicy, ProcessHandle, ProcessManagerClient

__all__ = [
    "FailurePolicy",
    "ProcessHandle",
    "ProcessManager",
    "ProcessManagerClient",
    "ProcessRequest",
    "ProcessResponse",
]
