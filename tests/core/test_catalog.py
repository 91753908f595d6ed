"""Where actions and graphs are found: ActionCatalog and GraphIndex.

Fixture folders live in ``tests/data/catalog`` (actions) and ``tests/data/graphs`` (graphs);
tests that need to change files on disk build their folders in ``tmp_path``.
"""

from __future__ import annotations

import importlib
import json
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from temoto import (
    Action,
    ActionCatalog,
    ActionEngine,
    GraphIndex,
    Result,
    load_graph,
    parse_graph,
    parse_umrf,
)
from temoto.errors import (
    ActionNotFoundError,
    ConfigError,
    GraphNotFoundError,
    PluginConflictError,
    PluginLoadError,
)

DATA = Path(__file__).resolve().parents[1] / "data"
ACTIONS = DATA / "catalog"
GRAPHS = DATA / "graphs"
WAIT = 10.0


def catalog(*folders: str | Path) -> ActionCatalog:
    return ActionCatalog(
        [ACTIONS / f if isinstance(f, str) else f for f in folders], use_entry_points=False
    )


def imported_action_modules(stem: str) -> list[str]:
    return [m for m in sys.modules if m.startswith("_temoto_action_") and m.endswith(f"_{stem}")]


def shout_graph(literal: str = "hey", name: str = "shout") -> Any:
    return parse_graph(
        {
            "graph_name": name,
            "actions": [
                {
                    "name": "TaGood",
                    "type": "sync",
                    "input_parameters": {"text": {"pvf_type": "string", "pvf_value": literal}},
                    "output_parameters": {"text_out": {"pvf_type": "string"}},
                }
            ],
        }
    )


# ================================================================ directory scanning


def test_scan_depth_is_two_levels() -> None:
    cat = catalog("depth")
    assert cat.names() == ["DepthOne", "DepthTwo", "DepthZero"]
    assert "DepthThree" not in cat  # depth/l1/l2/l3/d3.umrf.json is 3 levels down
    assert cat.find("DepthThree") is None
    assert cat.problems == []


def test_scan_depth_counts_from_the_given_folder() -> None:
    cat = ActionCatalog([ACTIONS / "depth" / "l1"], use_entry_points=False)
    assert "DepthThree" in cat  # now only 2 levels down


def test_not_a_directory_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError):
        ActionCatalog([tmp_path / "missing"], use_entry_points=False)
    file = tmp_path / "file.txt"
    file.write_text("x")
    with pytest.raises(ConfigError):
        ActionCatalog([file], use_entry_points=False)
    with pytest.raises(ConfigError):
        GraphIndex([tmp_path / "missing"])


def test_add_path_counts_descriptions(tmp_path: Path) -> None:
    cat = ActionCatalog(use_entry_points=False)
    assert cat.add_path(ACTIONS / "depth") == 3
    assert cat.add_path(ACTIONS / "good") == 1
    assert cat.add_path(tmp_path) == 0  # empty folder: logged, not an error
    assert cat.names() == ["DepthOne", "DepthTwo", "DepthZero", "TaGood"]


def test_add_path_count_ignores_sibling_folders_with_a_common_prefix(tmp_path: Path) -> None:
    for folder, name in (("acts", "TaOne"), ("acts2", "TaTwo")):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "x.umrf.json").write_text(json.dumps({"name": name, "type": "sync"}))
    cat = ActionCatalog(use_entry_points=False)
    if cat.add_path(tmp_path / "acts2") != 1:
        pytest.fail("precondition: acts2 holds one description")
    assert cat.add_path(tmp_path / "acts") == 1  # actual: 2 (acts2's TaTwo counted as well)


def test_refresh_sees_new_and_removed_files(tmp_path: Path) -> None:
    folder = tmp_path / "acts"
    folder.mkdir()
    first = folder / "ta_one.umrf.json"
    first.write_text(json.dumps({"name": "TaOne", "type": "sync"}))
    cat = ActionCatalog([folder], use_entry_points=False)
    assert cat.names() == ["TaOne"]
    (folder / "ta_two.umrf.json").write_text(json.dumps({"name": "TaTwo", "type": "sync"}))
    first.unlink()
    assert cat.names() == ["TaOne"]  # no polling
    cat.refresh()
    assert cat.names() == ["TaTwo"]


# ================================================================ lazy import


def test_description_is_indexed_without_importing_code() -> None:
    cat = catalog("broken", "good")
    assert "TaBroken" in cat
    desc = cat.find("TaBroken")
    assert desc is not None
    assert desc.name == "TaBroken"
    assert imported_action_modules("ta_broken") == []


def test_module_failing_at_import_raises_plugin_load_error_with_cause() -> None:
    cat = catalog("broken")
    with pytest.raises(PluginLoadError) as info:
        cat.load_class("TaBroken")
    assert isinstance(info.value.__cause__, RuntimeError)
    assert "on purpose" in str(info.value.__cause__)
    assert "TaBroken" in str(info.value)
    assert "ta_broken.py" in str(info.value)
    assert imported_action_modules("ta_broken") == []  # a failed import leaves nothing behind
    with pytest.raises(PluginLoadError):  # and is retried, not cached as a success
        cat.load_class("TaBroken")


def test_broken_action_fails_only_the_graphs_that_use_it() -> None:
    broken = parse_graph(
        {"graph_name": "uses_broken", "actions": [{"name": "TaBroken", "type": "sync"}]}
    )
    with ActionEngine("me", actions=catalog("broken", "good")) as engine:
        with pytest.raises(PluginLoadError) as info:
            engine.start(broken)
        assert isinstance(info.value.__cause__, RuntimeError)
        assert "uses_broken" not in engine.running_graphs()
        outcome = engine.run(shout_graph(), timeout=WAIT)
        assert outcome.result is Result.TRUE
        assert outcome.outputs == {"text_out": "hey!"}


def test_load_class_returns_the_class_once() -> None:
    cat = catalog("good")
    cls = cat.load_class("TaGood")
    assert issubclass(cls, Action)
    assert cls.__name__ == "TaGood"
    assert cat.load_class("TaGood") is cls


def test_two_catalogs_importing_one_file_at_once_both_get_the_class(tmp_path: Path) -> None:
    # the first importer's module is in sys.modules while its code runs: the second one must
    # wait for it, not take the half-made module ("defines no Action subclass", seen when two
    # engines of one process started graphs with the same action)
    folder = tmp_path / "ta_slow_import"
    folder.mkdir()
    (folder / "ta_slow_import.umrf.json").write_text(
        json.dumps({"name": "TaSlowImport", "type": "sync"})
    )
    (folder / "ta_slow_import.py").write_text(
        "import time\n"
        "from temoto import Action\n"
        "time.sleep(0.5)  # the window the second importer falls into\n"
        "class TaSlowImport(Action):\n"
        "    def on_run(self) -> bool:\n"
        "        return True\n"
    )
    got: dict[str, Any] = {}

    def load(which: str) -> None:
        try:
            got[which] = catalog(tmp_path).load_class("TaSlowImport")
        except Exception as err:
            got[which] = err

    first = threading.Thread(target=load, args=("first",))
    first.start()
    deadline = time.monotonic() + WAIT
    while not imported_action_modules("ta_slow_import") and time.monotonic() < deadline:
        time.sleep(0.005)  # the first import is under way
    assert imported_action_modules("ta_slow_import")
    load("second")
    first.join(WAIT)
    assert isinstance(got["first"], type), got
    assert got["second"] is got["first"], got


def test_missing_module_is_action_not_found_naming_expected_file() -> None:
    cat = catalog("orphan")
    assert cat.find("TaOrphan") is not None
    with pytest.raises(ActionNotFoundError) as info:
        cat.load_class("TaOrphan")
    message = str(info.value)
    assert "ta_orphan.py" in message
    assert "ta_orphan.umrf.json" in message
    g = parse_graph({"graph_name": "orphaned", "actions": [{"name": "TaOrphan", "type": "sync"}]})
    with (
        ActionEngine("me", actions=cat) as engine,
        pytest.raises(ActionNotFoundError, match=r"ta_orphan\.py"),
    ):
        engine.start(g)


def test_module_without_the_class_is_plugin_load_error() -> None:
    cat = catalog("noclass")
    with pytest.raises(PluginLoadError, match="no Action subclass named 'TaNoclass'"):
        cat.load_class("TaNoclass")


def test_unknown_action() -> None:
    cat = catalog("good")
    assert cat.find("Nope") is None
    with pytest.raises(ActionNotFoundError, match="Nope"):
        cat.load_class("Nope")


def test_description_named_plain_umrf_json_finds_its_module() -> None:
    cat = catalog("legacy_name")
    if "TaLegacyName" not in cat:
        pytest.fail("precondition: the description is indexed")
    cls = cat.load_class("TaLegacyName")  # actual: ActionNotFoundError "expected ta_legacy_name.py"
    assert cls.__name__ == "TaLegacyName"


# ================================================================ conflicts and problems


def test_same_action_in_two_folders_is_a_conflict_naming_both() -> None:
    cat = catalog("twin_a", "twin_b")
    assert "TaTwin" in cat
    for lookup in (cat.find, cat.load_class, cat.entry):
        with pytest.raises(PluginConflictError) as info:
            lookup("TaTwin")
        message = str(info.value)
        assert str(ACTIONS / "twin_a" / "ta_twin" / "ta_twin.umrf.json") in message
        assert str(ACTIONS / "twin_b" / "ta_twin" / "ta_twin.umrf.json") in message
    g = parse_graph({"graph_name": "twins", "actions": [{"name": "TaTwin", "type": "sync"}]})
    with ActionEngine("me", actions=cat) as engine, pytest.raises(PluginConflictError):
        engine.start(g)


def test_same_folder_twice_is_not_a_conflict() -> None:
    cat = catalog("twin_a", "twin_a")
    assert cat.load_class("TaTwin").__name__ == "TaTwin"
    cat.refresh()
    assert cat.entry("TaTwin").origin.endswith("ta_twin.umrf.json")


def test_unparseable_descriptions_are_listed_and_skipped() -> None:
    cat = catalog("mixed")
    assert cat.names() == ["TaFine"]
    problems = dict(cat.problems)
    assert set(problems) == {
        str(ACTIONS / "mixed" / "ta_no_type.umrf.json"),
        str(ACTIONS / "mixed" / "ta_syntax.umrf.json"),
    }
    assert "type" in problems[str(ACTIONS / "mixed" / "ta_no_type.umrf.json")]
    assert cat.load_class("TaFine").__name__ == "TaFine"


def test_register_in_code() -> None:
    class InCode(Action):
        def on_run(self) -> bool:
            return True

    cat = ActionCatalog(use_entry_points=False)
    cat.register(InCode, parse_umrf({"name": "InCode", "type": "sync"}))
    assert cat.names() == ["InCode"]
    assert cat.load_class("InCode") is InCode
    assert "registered in code" in cat.entry("InCode").origin
    cat.refresh()
    assert cat.load_class("InCode") is InCode  # survives a refresh
    assert [d.name for d in cat] == ["InCode"]


def test_register_rejects_non_actions() -> None:
    cat = ActionCatalog(use_entry_points=False)
    with pytest.raises(TypeError, match="not a subclass"):
        cat.register(dict, parse_umrf({"name": "Dict", "type": "sync"}))  # type: ignore[arg-type]


# ================================================================ GraphIndex


def test_graph_index_duplicate_different_graphs_conflict_on_get() -> None:
    index = GraphIndex([GRAPHS / "dup_a", GRAPHS / "dup_b"])
    assert index.names() == ["dup"]
    with pytest.raises(PluginConflictError) as info:
        index.get("dup")
    assert str(GRAPHS / "dup_a" / "dup.graph.json") in str(info.value)
    assert str(GRAPHS / "dup_b" / "dup.graph.json") in str(info.value)
    with (
        ActionEngine("me", actions=catalog("good"), graphs=index) as engine,
        pytest.raises(PluginConflictError),
    ):
        engine.start("dup")


def test_graph_index_equal_duplicates_are_fine() -> None:
    index = GraphIndex([GRAPHS / "same_a", GRAPHS / "same_b"])
    assert index.get("same").name == "same"
    assert len([g for g in index.all() if g.name == "same"]) == 2


def test_graph_index_problems_and_unknown_names() -> None:
    index = GraphIndex([GRAPHS / "same_b"])
    assert [Path(f).name for f, _ in index.problems] == ["broken.graph.json"]
    assert "broken" not in index.names()
    with pytest.raises(GraphNotFoundError, match="nope"):
        index.get("nope")


def test_graph_index_start_by_name() -> None:
    index = GraphIndex([GRAPHS / "same_a"])
    with ActionEngine("me", actions=catalog("good"), graphs=index) as engine:
        run = engine.start("same")
        assert engine.wait(run, timeout=WAIT) is Result.TRUE
        assert engine.outcome(run).outputs == {"text_out": "equal!"}
        assert {g.name for g in engine.indexed_graphs()} == {"same", "Shout"}


def test_find_subgraph_matches_by_signature() -> None:
    index = GraphIndex([GRAPHS / "same_a"])
    io = {
        "input_parameters": {"text": {"pvf_type": "string"}},
        "output_parameters": {"text_out": {"pvf_type": "string"}},
    }
    matching = parse_umrf({"name": "Shout", "type": "sync", **io})
    assert index.find_subgraph(matching) is index.get("Shout")
    wrong_inputs = parse_umrf(
        {"name": "Shout", "type": "sync", "output_parameters": io["output_parameters"]}
    )
    assert index.find_subgraph(wrong_inputs) is None
    wrong_name = parse_umrf({"name": "Whisper", "type": "sync", **io})
    assert index.find_subgraph(wrong_name) is None


def test_find_subgraph_picks_the_signature_among_same_named_graphs() -> None:
    index = GraphIndex([GRAPHS / "same_a"])
    other = parse_graph(
        {
            "graph_name": "Shout",
            "actions": [
                {
                    "name": "TaGood",
                    "type": "sync",
                    "input_parameters": {"text": {"pvf_type": "string", "pvf_value": "fixed"}},
                    "output_parameters": {"text_out": {"pvf_type": "string"}},
                }
            ],
        }
    )
    index.add(other)  # same name, signature: no inputs → text_out
    with pytest.raises(PluginConflictError):
        index.get("Shout")
    action = parse_umrf(
        {"name": "Shout", "type": "sync", "output_parameters": {"text_out": {"pvf_type": "string"}}}
    )
    assert index.find_subgraph(action) is other


def test_indexed_subgraph_runs_inside_a_graph() -> None:
    top = parse_graph(
        {
            "graph_name": "top",
            "actions": [
                {
                    "name": "Shout",
                    "type": "sync",
                    "input_parameters": {"text": {"pvf_type": "string", "pvf_value": "hi"}},
                    "output_parameters": {"text_out": {"pvf_type": "string"}},
                }
            ],
        }
    )
    with ActionEngine("me", actions=catalog("good"), graphs=[GRAPHS / "same_a"]) as engine:
        outcome = engine.run(top, timeout=WAIT)
        assert outcome.result is Result.TRUE
        assert outcome.outputs == {"text_out": "hi!"}
        assert "top__Shout__0" in engine.running_graphs()


def test_graph_index_memory_graphs_survive_refresh() -> None:
    index = GraphIndex([GRAPHS / "same_a"])
    index.add(shout_graph(name="in_memory"))
    index.refresh()
    assert "in_memory" in index.names()
    assert load_graph(GRAPHS / "same_a" / "same.graph.json") == index.get("same")


# ================================================================ entry points


@pytest.fixture
def installed_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """A package offered through the ``temoto.action_packages`` entry-point group.

    Made to look installed: the package and a ``*.dist-info`` with ``entry_points.txt`` on a
    directory prepended to ``sys.path``.
    """
    package = "temoto_test_ep_actions"
    root = tmp_path / "site"
    action_dir = root / package / "ta_from_ep"
    action_dir.mkdir(parents=True)
    (root / package / "__init__.py").write_text("")
    (action_dir / "__init__.py").write_text("")
    (action_dir / "ta_from_ep.umrf.json").write_text(
        json.dumps({"name": "TaFromEp", "type": "sync"})
    )
    (action_dir / "ta_from_ep.py").write_text(
        "from temoto import Action\n\n\nclass TaFromEp(Action):\n    def on_run(self) -> bool:\n"
        "        return True\n"
    )
    dist = root / "temoto_test_ep_actions-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: temoto-test-ep-actions\nVersion: 0.1\n"
    )
    (dist / "entry_points.txt").write_text(f"[temoto.action_packages]\ndemo = {package}\n")
    monkeypatch.syspath_prepend(str(root))
    importlib.invalidate_caches()
    yield package
    for name in [m for m in sys.modules if m == package or m.startswith(package + ".")]:
        del sys.modules[name]


def test_entry_point_packages_are_indexed_and_loaded(installed_package: str) -> None:
    cat = ActionCatalog()
    assert "TaFromEp" in cat
    entry = cat.entry("TaFromEp")
    assert entry.origin.endswith("ta_from_ep.umrf.json")
    assert entry.module == f"{installed_package}.ta_from_ep.ta_from_ep"
    assert f"{installed_package}.ta_from_ep.ta_from_ep" not in sys.modules  # not imported yet
    cls = cat.load_class("TaFromEp")
    assert cls.__module__ == f"{installed_package}.ta_from_ep.ta_from_ep"
    g = parse_graph({"graph_name": "ep", "actions": [{"name": "TaFromEp", "type": "sync"}]})
    with ActionEngine("me", actions=cat) as engine:
        assert engine.run(g, timeout=WAIT).result is Result.TRUE


def test_entry_points_can_be_switched_off(installed_package: str) -> None:
    assert "TaFromEp" not in ActionCatalog(use_entry_points=False)
