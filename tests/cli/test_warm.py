"""``python -m mpcrl_lite.cli.warm``: every kernel in a group, the groups compiled side by side
in worker processes, then all loaded in the calling process."""

from __future__ import annotations

from mpcrl_lite.cli import warm
from mpcrl_lite.decentralized import coordination_kernel
from mpcrl_lite.mpc.backends import kernel, kernel_sizes
from mpcrl_lite.sim import exploration_kernel


def test_the_groups_cover_the_generic_kernels_and_every_sized_copy():
    groups = warm._groups()
    assert groups[0] == "generic"
    assert {tuple(int(v) for v in g.split("x")) for g in groups[1:]} == \
        set(kernel_sizes.SPECIALISED_SIZES)


def test_warm_up_in_two_workers_leaves_every_kernel_loaded_here():
    """The workers fill the cache (with ``make setup`` run before: only load it); then this
    process has every kernel of every group loaded."""
    assert warm.warm_up(workers=2) > 0.0
    assert kernel.K.solve_rows.signatures and kernel.K.sensitivity_rows.signatures
    for n, N in kernel_sizes.SPECIALISED_SIZES:
        copy = kernel_sizes.kernels(n, N)
        assert copy.solve_rows.signatures and copy.sensitivity_rows.signatures
    assert exploration_kernel.explore_rows.signatures
    assert exploration_kernel.project_rows.signatures
    assert coordination_kernel.coordinate.signatures
