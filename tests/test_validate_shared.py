"""``temoto validate`` on shared graphs: no fleet link needed, ``--actor`` checks one actor.

Upstream's three-actor graph (Actor A relays, Actor B adds, Actor C compares) is checked with
every action folder, with a folder holding only Actor A's action, and as each actor.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest

from temoto.cli import main
from temoto.core.catalog import ActionCatalog, GraphIndex
from temoto.core.documents import load_graph
from temoto.core.planning import Planner
from temoto.core.umrf import Umrf
from temoto.errors import ActionNotFoundError

ROOT = Path(__file__).resolve().parents[1]
UPSTREAM = ROOT.parent / "shared" / "conformance" / "umrf" / "upstream"
MULTI = UPSTREAM / "actionengine_test_engine_test_multi_actor.graph.json"
ACTIONS = ROOT / "examples" / "actions" / "conformance"

pytestmark = pytest.mark.skipif(not MULTI.is_file(), reason=f"no conformance data at {MULTI}")


@pytest.fixture
def only_actor_a(tmp_path: Path) -> Path:
    """An action folder with Actor A's TaRelayString only."""
    folder = tmp_path / "actor_a"
    folder.mkdir()
    for name in ("ta_relay_string.py", "ta_relay_string.umrf.json"):
        shutil.copy(ACTIONS / name, folder / name)
    return folder


def multi_doc() -> dict[str, Any]:
    doc: dict[str, Any] = json.loads(MULTI.read_text(encoding="utf-8"))
    return doc


def action(doc: dict[str, Any], name: str) -> dict[str, Any]:
    found: dict[str, Any] = next(a for a in doc["actions"] if a["name"] == name)
    return found


def write(tmp_path: Path, doc: dict[str, Any]) -> str:
    path = tmp_path / "shared.graph.json"
    path.write_text(json.dumps(doc), encoding="utf-8")
    return str(path)


def test_the_structure_of_a_shared_graph_is_checked_without_a_fleet(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["validate", str(MULTI)]) == 0
    out = capsys.readouterr().out
    assert out.endswith("ok (3 actions; shared by 'Actor A', 'Actor B', 'Actor C')\n")


def test_every_actors_actions_resolve_with_all_folders(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", str(MULTI), "--actions", str(ACTIONS)]) == 0
    captured = capsys.readouterr()
    assert "3 resolved here, 0 left to their actors" in captured.out
    assert "note:" not in captured.out
    assert "fleet link" not in captured.err


def test_actions_that_do_not_resolve_here_are_named_as_other_actors(
    only_actor_a: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["validate", str(MULTI), "--actions", str(only_actor_a)]) == 0
    out = capsys.readouterr().out
    assert f"{MULTI}: note: 'TaAddString_0' is left to actor 'Actor B': no action" in out
    assert "'TaCompareString_0' is left to actor 'Actor C'" in out
    assert "TaRelayString_0" not in out  # it resolved here
    assert "1 resolved here, 2 left to their actors" in out


@pytest.mark.parametrize(
    ("actor", "code", "names"),
    [("Actor A", 0, ""), ("Actor B", 2, "TaAddString"), ("Actor C", 2, "TaCompareString")],
)
def test_actor_checks_that_actors_actions_only(
    only_actor_a: Path,
    capsys: pytest.CaptureFixture[str],
    actor: str,
    code: int,
    names: str,
) -> None:
    argv = ["validate", str(MULTI), "--actions", str(only_actor_a), "--actor", actor]
    assert main(argv) == code
    captured = capsys.readouterr()
    if code == 0:
        assert f"actor '{actor}' has 1 resolved, the other actors' were not checked" in (
            captured.out
        )
    else:
        assert f"error: {MULTI}: graph 'engine_test_multi_actor': action '{names}_0'" in (
            captured.err
        )
        assert f"no action description and no indexed graph named '{names}'" in captured.err
        assert "Traceback" not in captured.err


def test_an_actor_the_graph_does_not_name_is_invalid(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", str(MULTI), "--actor", "Actor D"]) == 2
    err = capsys.readouterr().err
    assert str(MULTI) in err
    assert "no actions for actor 'Actor D'" in err
    assert "'Actor A', 'Actor B', 'Actor C'" in err


def test_an_action_without_actor_must_resolve_here(
    tmp_path: Path, only_actor_a: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = multi_doc()
    del action(doc, "TaAddString")["actor"]  # runs on every actor: it must resolve everywhere
    assert main(["validate", write(tmp_path, doc), "--actions", str(only_actor_a)]) == 2
    assert "named 'TaAddString'" in capsys.readouterr().err


def test_a_parameter_mismatch_is_a_note_for_others_and_an_error_for_the_actor(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = multi_doc()
    compare = action(doc, "TaCompareString")
    compare["input_parameters"]["str_c"] = {"pvf_type": "string", "pvf_value": "x"}
    path = write(tmp_path, doc)
    assert main(["validate", path, "--actions", str(ACTIONS)]) == 0
    out = capsys.readouterr().out
    assert "'TaCompareString_0' is left to actor 'Actor C': does not match the description" in out
    assert "has inputs str_c" in out
    assert main(["validate", path, "--actions", str(ACTIONS), "--actor", "Actor C"]) == 2
    assert "has inputs str_c" in capsys.readouterr().err


def test_a_structural_error_in_a_shared_graph_is_still_an_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = multi_doc()
    action(doc, "TaAddString")["children"][0]["remap"][0]["from"] = "no_such_output"
    assert main(["validate", write(tmp_path, doc), "--actions", str(ACTIONS)]) == 2
    assert "no_such_output" in capsys.readouterr().err


def test_the_legacy_shared_graph_validates_too(capsys: pytest.CaptureFixture[str]) -> None:
    legacy = UPSTREAM / "legacy_sharedgraphdemo_shared_graph_test_1_multi_actor.umrfg.json"
    assert main(["validate", str(legacy), "--actor", "actor_2"]) == 0
    assert "shared by 'actor_1', 'actor_2'" in capsys.readouterr().out


# --- the planner underneath ---------------------------------------------------------------------


def test_a_planner_with_elsewhere_resolves_what_it_can_and_reports_the_rest(
    only_actor_a: Path,
) -> None:
    seen: list[tuple[str, str, str]] = []

    def elsewhere(umrf: Umrf, why: str) -> None:
        seen.append((umrf.full_name, umrf.actor, why))

    planner = Planner("", ActionCatalog([only_actor_a]), GraphIndex(), elsewhere=elsewhere)
    plan = planner.plan(load_graph(MULTI))
    kinds = {name: how.kind.name for name, how in plan.actions.items()}
    assert kinds == {
        "TaRelayString_0": "LOCAL",
        "TaAddString_0": "REMOTE",
        "TaCompareString_0": "REMOTE",
    }
    assert [(n, a) for n, a, _ in seen] == [
        ("TaAddString_0", "Actor B"),
        ("TaCompareString_0", "Actor C"),
    ]
    assert seen[0][2] == "no action description and no indexed graph named 'TaAddString'"


def test_a_planner_without_elsewhere_does_not_look_at_other_actors(only_actor_a: Path) -> None:
    planner = Planner("Actor A", ActionCatalog([only_actor_a]), GraphIndex(), remote=True)
    plan = planner.plan(load_graph(MULTI))
    assert plan.actions["TaAddString_0"].kind.name == "REMOTE"
    with pytest.raises(ActionNotFoundError, match="TaRelayString"):
        Planner("Actor A", ActionCatalog(), GraphIndex(), remote=True).plan(load_graph(MULTI))
