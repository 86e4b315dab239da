"""The training loader's resumable state: the frame order is a function of (seed, step), so the state is those and
a checkpoint of another order is refused."""

from __future__ import annotations

import pytest

from framework.errors import SplatrigError
from framework.lightning.data import StepLoader, StepSampler


def _loader(n: int, seed: int, step: int) -> StepLoader:
    return StepLoader(list(range(n)), sampler=StepSampler(n, seed, lambda: step, num_samples=8))


def test_state_is_the_order_and_the_position() -> None:
    loader = _loader(10, seed=3, step=17)
    assert loader.state_dict() == {"seed": 3, "items": 10, "step": 17}
    resumed = _loader(10, seed=3, step=17)
    resumed.load_state_dict(loader.state_dict())
    # the resumed loader yields what the uninterrupted one yields from that step: the sampler's own draw at 17..24
    assert list(resumed.sampler) == StepSampler(10, 3).indices(17, 8)


@pytest.mark.parametrize(("seed", "n"), [(4, 10), (3, 11)])
def test_another_order_is_refused(seed: int, n: int) -> None:
    with pytest.raises(SplatrigError, match="frame order"):
        _loader(n, seed=seed, step=0).load_state_dict(_loader(10, seed=3, step=5).state_dict())
