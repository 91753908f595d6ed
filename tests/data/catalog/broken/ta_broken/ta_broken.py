"""A module that fails at import (catalog test fixture): only loading it may fail."""

raise RuntimeError("ta_broken fails at import on purpose")
