"""The learners train with the reward variant ``ipf-time`` by name (issue 16)."""

from __future__ import annotations

import pytest

from learners.algorithms import REWARD_NAMES
from learners.train import TrainConfig


def test_the_learners_train_with_the_variant_by_name() -> None:
    assert "ipf-time" in REWARD_NAMES
    assert TrainConfig(algo="bicnet", reward="ipf-time").reward == "ipf-time"
    with pytest.raises(ValueError, match="unknown reward 'ipf-tim'"):
        TrainConfig(algo="bicnet", reward="ipf-tim")
