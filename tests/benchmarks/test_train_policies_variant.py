"""``benchmarks/train_policies.py --reward`` takes the reward variant ``ipf-time`` (issue 16)."""

from __future__ import annotations

import pytest
from benchmark_scripts import load

train_policies = load("train_policies")


@pytest.mark.parametrize(("reward", "accepted"), [("ipf-time", True), ("ipf-tim", False)])
def test_the_reward_variant_is_a_choice(reward: str, accepted: bool, capsys) -> None:
    # a bad --tag stops main() right after the arguments are read, before any training
    with pytest.raises(SystemExit) as exc:
        train_policies.main(["--scenario", "3v3", "--algo", "bicnet", "--reward", reward,
                             "--episodes", "10", "--tag", "../up"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert ("--tag" in err and "invalid choice" not in err) if accepted else (
        "invalid choice: 'ipf-tim'" in err)
