"""mpcrl_lite: MPC-based reinforcement learning for a multi-agent battery storage system.

The package follows the data flow of the experiment::

    config -> prices / model -> mpc -> solvers -> sensitivity -> lstd -> dpg -> experiment
                                                                         -> history -> plots / widgets
"""

from .config import LearningConfig, MPCConfig, SystemConfig
from .theta import Theta

__all__ = ["LearningConfig", "MPCConfig", "SystemConfig", "Theta"]
__version__ = "0.1.0"
