"""Hot paths with an optional compiled twin (reserved; the Cython build comes later).

``COMPILED`` tells whether the compiled modules are in use.
"""

from __future__ import annotations

COMPILED = False
