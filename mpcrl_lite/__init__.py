"""mpcrl_lite: MPC-based reinforcement learning for a multi-agent battery storage system.

The package follows the data flow of the experiment, one way (``tests/test_architecture.py``
holds the layers)::

    config -> prices / model -> mpc -> solution <- back-ends (ipopt, batch, kernel) -> solvers
           -> sensitivity -> closed_loop -> record -> lstd / dpg -> learner -> experiment,
              decentralized, baselines, causal -> history -> plots -> widgets / report / site
"""

from .config import LearningConfig, MPCConfig, SystemConfig
from .theta import Theta

__all__ = ["LearningConfig", "MPCConfig", "SystemConfig", "Theta"]
from ._util.version import __version__
