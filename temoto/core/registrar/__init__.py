"""The Resource Registrar: counted, hierarchical, crash-proof resources (``docs/registrar.md``).

Every resource manager is a :class:`ResourceServer` on a :class:`Registrar`; consumers ``call``
for resources and ``release`` them.
"""

from __future__ import annotations

from temoto.core.registrar.messages import (
    Reference,
    Resource,
    ResourceInfo,
    Status,
    StatusUpdate,
)
from temoto.core.registrar.registry import Registrar
from temoto.core.registrar.server import LoadContext, RegistrarAPI, ResourceServer

__all__ = [
    "LoadContext",
    "Reference",
    "Registrar",
    "RegistrarAPI",
    "Resource",
    "ResourceInfo",
    "ResourceServer",
    "Status",
    "StatusUpdate",
]
