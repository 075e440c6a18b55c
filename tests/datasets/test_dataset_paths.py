"""A dataset's own metadata never moves a write or a read outside its root: the path templates of
meta/info.json are checked, for each video feature, before any command reads or writes through them."""

import json
import shutil

import pytest

from lerobot_condground.cli import main

VIDEO = "observation.images.top"


def tampered(src, dst, **info_changes):
    shutil.copytree(src, dst)
    info_file = dst / "meta" / "info.json"
    info = json.loads(info_file.read_text())
    if "rename_video" in info_changes:
        info["features"][info_changes.pop("rename_video")] = info["features"].pop(VIDEO)
    info.update(info_changes)
    info_file.write_text(json.dumps(info, indent=2))
    return dst


@pytest.fixture
def victim(tmp_path):
    """A user's file where a hostile template points; it must come out of every command unchanged."""
    folder = tmp_path / "victim"
    (folder / "chunk-000").mkdir(parents=True)
    target = folder / "chunk-000" / "file-000.parquet"
    target.write_text("the user's own file")
    yield folder
    assert target.read_text() == "the user's own file"
    assert sorted(p.name for p in folder.rglob("*")) == ["chunk-000", "file-000.parquet"]


def hostile_datasets(plain_dataset, tmp_path, victim):
    outside = f"{victim}/chunk-{{chunk_index:03d}}/file-{{file_index:03d}}.parquet"
    return {
        "absolute data_path": (
            tampered(plain_dataset, tmp_path / "absolute", data_path=outside),
            f"data_path '{outside}' names '{victim}/chunk-000/file-000.parquet', outside the dataset's root",
        ),
        "dotdot video_path": (
            tampered(plain_dataset, tmp_path / "dotdot", video_path="../victim/{video_key}.mp4"),
            "video_path '../victim/{video_key}.mp4' names '../victim/observation.images.top.mp4', outside",
        ),
        "string indices": (
            tampered(
                plain_dataset, tmp_path / "indices", data_path="data/{chunk_index}/{file_index:03d}.parquet"
            ),
            "formats 'chunk_index' without an integer format",
        ),
        "feature name": (
            tampered(plain_dataset, tmp_path / "feature", rename_video="observation.images/../../../victim"),
            "(for feature 'observation.images/../../../victim')",
        ),
    }


def test_every_command_refuses_templates_that_leave_the_root(
    plain_dataset, act_checkpoint, tmp_path, victim, capsys
):
    for name, (root, message) in hostile_datasets(plain_dataset, tmp_path, victim).items():
        before = sorted(p.relative_to(root) for p in root.rglob("*"))
        data = ["--dataset.repo_id=local/test_plain", f"--dataset.root={root}"]
        commands = {
            # Resuming a recording would write its next episodes by the templates.
            "record": ["record", "--env.task=PickPlaceRandomBin-v0", "--env.condition=full_mixed", *data,
                       "--dataset.num_episodes=2", "--dataset.labels=false", "--progress=false"],
            "augment": ["augment", *data, f"--output.root={tmp_path / 'out' / name}"],
            "fit": ["fit", f"--policy.path={act_checkpoint}", *data, f"--output_dir={tmp_path / 'fit' / name}"],
            "train": ["train", "--policy.type=act", "--policy.push_to_hub=false", *data, f"--output_dir={tmp_path / 'train' / name}"],
            # Whatever spelling names the root LeRobot opens (here draccus's "--flag value").
            "train, root as two words": ["train", "--policy.type=act", "--policy.push_to_hub=false",
                                         "--dataset.repo_id=local/test_plain", "--dataset.root", str(root),
                                         f"--output_dir={tmp_path / 'train' / name}"],
            "prompts": ["prompts", *data, f"--output.root={tmp_path / 'prompts' / name}"],
        }  # fmt: skip
        for command, args in commands.items():
            assert main(args) == 2, (name, command)
            last = capsys.readouterr().err.strip().splitlines()[-1]
            assert f"{root / 'meta' / 'info.json'}: " in last and message in last, (name, command, last)
        assert sorted(p.relative_to(root) for p in root.rglob("*")) == before, name
        assert not (tmp_path / "out").exists() and not (tmp_path / "train").exists()
        assert not (tmp_path / "prompts").exists() and not (tmp_path / "fit").exists()


def test_a_dataset_whose_info_links_outside_its_root_is_refused(tmp_path):
    from lerobot_condground.core.trust import check_dataset_paths

    outside = tmp_path / "elsewhere" / "info.json"
    outside.parent.mkdir()
    outside.write_text(
        json.dumps({"data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"})
    )
    root = tmp_path / "ds"
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").symlink_to(outside)
    with pytest.raises(PermissionError, match="info.json links outside the dataset's root"):
        check_dataset_paths(root)
