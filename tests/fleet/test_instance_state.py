"""What an instance keeps across a restart: ``--state-dir`` (registrar journal, world model)."""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import pytest

from temoto.cli.fleet import StateFiles, add_state_options, state_files
from temoto.errors import ConfigError, ResourceBusyError
from temoto.instance import Instance
from temoto.managers.context import Pose
from temoto.transport import InProcessTransport

KEY = bytes(range(32))
_buses = itertools.count()


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_state_options(parser)
    return parser.parse_args(list(argv))


def start(files: StateFiles) -> Instance:
    return Instance(
        "keeper",
        transport=InProcessTransport(f"state-{next(_buses)}"),
        key=KEY,
        catalog=files.catalog,
        world=files.world,
        reliability_file=files.reliability,
    )


def test_the_world_model_survives_a_restart_of_the_instance(tmp_path: Path) -> None:
    files = state_files(parse("--state-dir", str(tmp_path / "state")))
    state = tmp_path / "state"
    assert files == StateFiles(
        state / "registrar.journal", state / "world.journal", state / "reliability.json"
    )
    with start(files) as first:
        first.context.add("map", "map")
        first.context.add("dock", "object", "map", Pose(4.0, -1.0))
        with pytest.raises(ResourceBusyError):  # one instance per state directory
            start(files)
    with start(files) as second:
        assert second.context.path("dock") == ["map", "dock"]
        assert second.context.world_pose("dock").x == pytest.approx(4.0)
    assert files.catalog is not None
    assert files.catalog.is_file()


def test_explicit_files_win_and_nothing_is_kept_without_options(tmp_path: Path) -> None:
    mine = tmp_path / "mine.journal"
    files = state_files(parse("--state-dir", str(tmp_path), "--world", str(mine)))
    assert files == StateFiles(tmp_path / "registrar.journal", mine, tmp_path / "reliability.json")
    assert state_files(parse()) == StateFiles(None, None, None)


def test_a_state_dir_that_cannot_be_made_is_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(ConfigError, match=r"--state-dir .*file/state"):
        state_files(parse("--state-dir", str(blocker / "state")))
