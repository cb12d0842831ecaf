"""Re-exports `comexp.method.perception`: depth image -> region, contacts, pose."""

from comexp.method.perception import *  # noqa: F403 - the very names of its __all__
from comexp.method.perception import __all__  # noqa: F401
