"""The shared config groups refuse values that would act outside what the user asked for."""

import pytest

from lerobot_condground.core.configs import DatasetRefConfig, PolicyRefConfig, check_seed, comma_items


@pytest.mark.parametrize("repo_id", ["../../escape", "local/../../escape", "../x", "a/..", "/abs/path"])
def test_a_repo_id_cannot_reach_outside_lerobot_home(repo_id, tmp_path):
    with pytest.raises(ValueError, match=f"repo_id={repo_id!r} is not a hub id"):
        DatasetRefConfig(repo_id=repo_id).path()
    assert (
        DatasetRefConfig(repo_id=repo_id, root=str(tmp_path)).path() == tmp_path
    )  # a root is taken as given


def test_seeds_out_of_range_name_the_flag():
    check_seed("--seed", 0, 10)
    check_seed("--seed", 2**63 - 10, 10)
    for first in (-1, 2**63 - 9):
        with pytest.raises(ValueError, match=f"--seed={first} is not allowed; allowed: a seed from 0 to"):
            check_seed("--seed", first, 10)


@pytest.mark.parametrize("text", ["a,,b", "a,b,", ",a", " , "])
def test_an_empty_item_in_a_list_flag_is_refused(text):
    with pytest.raises(ValueError, match=r"--x=.* has an empty item"):
        comma_items(text, "--x")


def test_list_flags_everywhere_refuse_empty_items():
    """Every command's list flag goes through comma_items: a typo is one error, not a silently shorter list."""
    from lerobot_condground.core.routing import parse_episodes
    from lerobot_condground.diagnosis.report import parse_report_args
    from lerobot_condground.evaluation.subgoals import parse_subgoals
    from lerobot_condground.evaluation.sweep import parse_conditions

    for call, flag in (
        (lambda: parse_episodes("procedure,,place"), "subgoal="),
        (lambda: parse_subgoals("route,,place"), "--subgoals="),
        (lambda: parse_conditions("clean,,full_mixed"), "--sweep.conditions="),
        (lambda: parse_conditions("clean;;full_mixed"), "--sweep.conditions="),
        (lambda: PolicyRefConfig(paths="a,b,").checkpoints(), "--policy.paths="),
        (lambda: parse_report_args(["--input_dir=a,,b"]), "--input_dir="),
    ):
        with pytest.raises(ValueError, match=f"{flag}.* has an empty item"):
            call()
    assert comma_items(" a , b ", "--x") == ["a", "b"] and comma_items(" ", "--x") == []
    assert PolicyRefConfig(path="p", paths="a, b").checkpoints() == ["p", "a", "b"]
