"""The shared config groups refuse values that would act outside what the user asked for."""

import pytest

from lerobot_condground.core.configs import DatasetRefConfig, check_seed


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
