"""Re-exports `comexp.experiment.simulator`: the simulator interface, push protocol."""

from comexp.experiment.simulator import *  # noqa: F403 - the very names of its __all__
from comexp.experiment.simulator import __all__  # noqa: F401
