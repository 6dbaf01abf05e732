"""The planner's compiled kinematics give `firmware_if.kinematics`' answers."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_if import kinematics as kin
from firmware_if.hand import load_hand
from service.localization import chain_kernels

CHAINS = [*load_hand("three-finger").fingers, load_hand("planar"), load_hand("spatial")]


@pytest.mark.parametrize("chain", CHAINS, ids=lambda c: c.name)
def test_jacobians_and_inverse_kinematics_match_the_numpy_kinematics(chain):
    rng = np.random.default_rng(3)
    q = rng.uniform(chain.lower, chain.upper, (40, len(chain.lower)))
    np.testing.assert_allclose(chain_kernels.jacobians(chain, q), kin.jacobian(chain, q),
                               atol=1e-14)
    # near and beyond the workspace: the same reach, and the same angles where reached
    spread = [1.0, 0.0 if chain.planar else 1.0, 1.0]
    targets = kin.forward(chain, q) + rng.normal(0, 0.004, (40, 3)) * spread
    q0 = np.broadcast_to(np.array(chain.home), q.shape)
    for rows in (slice(0, 2), slice(2, 3), slice(3, 40)):  # batches stop together
        reference = kin.inverse(chain, targets[rows], q0[rows])
        angles, reached = chain_kernels.inverse(chain, targets[rows], q0[rows])
        np.testing.assert_array_equal(reached, reference.reachable)
        np.testing.assert_allclose(angles[reached], reference.q[reached], atol=1e-9)
        assert np.all((angles >= chain.lower) & (angles <= chain.upper))
    assert 0 < np.mean(kin.inverse(chain, targets, q0).reachable) < 1


def test_the_solver_is_compiled_once_whatever_its_start_angles_are():
    """A read-only start (one broadcast row: contiguous, not writable) is a type of its own
    to numba: the first turn of three fingers on blob compiled the solver again inside one
    decision, 1.5 s on an empty cache (seed 0, step 6)."""
    chain = CHAINS[0]
    home = np.array(chain.home)
    target = kin.forward(chain, home[np.newaxis])
    read_only = np.broadcast_to(home, (1, len(home)))
    assert read_only.flags.c_contiguous and not read_only.flags.writeable
    for q0 in (home[np.newaxis].copy(), read_only, np.broadcast_to(home, (2, len(home)))):
        chain_kernels.inverse(chain, np.repeat(target, len(q0), axis=0), q0)
    assert len(chain_kernels._solve_ik.signatures) == 1
