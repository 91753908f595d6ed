"""The Context Manager's tree: changes, checks, queries, the merge rule, tombstones, poses."""

from __future__ import annotations

import math

import pytest

from temoto.clock import ManualClock
from temoto.errors import ContextCycleError, ContextError, ContextItemNotFoundError
from temoto.managers.context import ContextManager, ContextTree, Item, Pose, Removal


@pytest.fixture
def cm() -> ContextManager:
    manager = ContextManager("r1", clock=ManualClock())
    manager.add("map", "map")
    manager.add("room", "map", "map", Pose(10.0, 0.0))
    manager.add("table", "object", "room", Pose(1.0, 2.0))
    manager.add("cup", "object", "table", Pose(0.0, 0.0, 0.8))
    manager.add("robot", "robot", "map", Pose.from_euler(5.0, 0.0, yaw=math.pi / 2))
    yield manager
    manager.close()


def test_add_and_queries(cm: ContextManager) -> None:
    cup = cm.get("cup")
    assert (cup.type, cup.parent, cup.maintainer, cup.writer) == ("object", "table", "r1", "r1")
    assert cup.stamp_us == 1_700_000_000_000_000
    assert [i.name for i in cm.find("object")] == ["cup", "table"]
    assert cm.find("nothing") == []
    assert cm.types() == {"map": 2, "object": 2, "robot": 1}
    assert [i.name for i in cm.children()] == ["map"]
    assert [i.name for i in cm.children("map")] == ["robot", "room"]
    assert [i.name for i in cm.subtree()] == ["map", "robot", "room", "table", "cup"]
    assert [i.name for i in cm.subtree("room")] == ["room", "table", "cup"]
    assert [i.name for i in cm.subtree("room", depth=1)] == ["room", "table"]
    assert [i.name for i in cm.subtree("", depth=0)] == ["map"]
    assert cm.path("cup") == ["map", "room", "table", "cup"]
    world = cm.world_pose("cup")
    assert (world.x, world.y, world.z) == pytest.approx((11.0, 2.0, 0.8))
    assert len(cm) == 5
    assert "cup" in cm
    assert "saucer" not in cm
    assert cm.detached() == []


def test_attributes_and_update(cm: ContextManager) -> None:
    cm.add("bin", "object", "room", attributes={"colour": "red", "volume_l": 30})
    assert cm.get("bin").attributes == {"colour": "red", "volume_l": 30}
    before = cm.get("bin")
    after = cm.update("bin", pose=Pose(1.0), kind="container", attributes={"full": True})
    assert after.version > before.version
    assert (after.type, after.pose.x, after.attributes) == ("container", 1.0, {"full": True})
    assert cm.find("object") == [cm.get("cup"), cm.get("table")]
    with pytest.raises(ValueError, match="JSON"):
        cm.update("bin", attributes={"x": math.nan})
    with pytest.raises(TypeError):
        cm.add("x", "object", attributes=["not", "a", "mapping"])  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("name", "kind", "error"),
    [
        ("", "object", ValueError),
        ("a\nb", "object", ValueError),
        ("x" * 257, "object", ValueError),
        (3, "object", TypeError),
        ("ok", "", ValueError),
    ],
)
def test_bad_names(cm: ContextManager, name: object, kind: str, error: type[Exception]) -> None:
    with pytest.raises(error):
        cm.add(name, kind)  # type: ignore[arg-type]
    assert len(cm) == 5


def test_refusals_leave_the_tree_unchanged(cm: ContextManager) -> None:
    dump = cm.dump()
    with pytest.raises(ContextError, match="exists already"):
        cm.add("cup", "object", "map")
    with pytest.raises(ContextItemNotFoundError, match="parent 'shelf'"):
        cm.add("book", "object", "shelf")
    with pytest.raises(ContextCycleError):
        cm.add("book", "object", "book")
    with pytest.raises(ContextCycleError, match="below"):
        cm.move("room", "cup")
    with pytest.raises(ContextCycleError):
        cm.move("room", "room")
    with pytest.raises(ContextItemNotFoundError):
        cm.move("room", "garage")
    with pytest.raises(ContextItemNotFoundError):
        cm.move("garage", "room")
    with pytest.raises(ContextError, match="has 1 children"):
        cm.remove("table")
    with pytest.raises(ContextItemNotFoundError):
        cm.remove("garage")
    with pytest.raises(ContextItemNotFoundError):
        cm.update("garage", pose=Pose())
    with pytest.raises(LookupError):
        cm.get("garage")
    with pytest.raises(ValueError, match="depth"):
        cm.subtree("map", depth=-1)
    assert cm.dump() == dump


def test_move_keeps_the_world_pose_unless_given(cm: ContextManager) -> None:
    # the robot (at (5, 0), facing +y) picks up the cup: it stays where it was in the world
    before = cm.world_pose("cup")
    moved = cm.move("cup", "robot")
    assert moved.parent == "robot"
    after = cm.world_pose("cup")
    assert after.as_tuple() == pytest.approx(before.as_tuple(), abs=1e-9)
    assert cm.path("cup") == ["map", "robot", "cup"]
    assert [i.name for i in cm.subtree("table")] == ["table"]
    # given a pose, it is relative to the new parent
    cm.move("cup", "table", Pose(0.1, 0.0, 0.8))
    assert cm.world_pose("cup").x == pytest.approx(11.1)
    # to a root
    cm.move("cup", "")
    assert cm.world_pose("cup").as_tuple() == pytest.approx(cm.get("cup").pose.as_tuple())
    assert cm.get("cup").pose.x == pytest.approx(11.1)


def test_remove_refused_or_cascading(cm: ContextManager) -> None:
    assert cm.remove("cup") == ["cup"]
    assert "cup" not in cm
    removal = cm.removed("cup")
    assert isinstance(removal, Removal)
    assert removal.writer == "r1"
    cm.add("cup", "object", "table")  # a removed name can be added again
    assert cm.removed("cup") is None
    assert cm.remove("room", cascade=True) == ["cup", "table", "room"]
    assert [i.name for i in cm.items()] == ["map", "robot"]
    assert cm.find("object") == []


def test_newest_wins_and_tombstones() -> None:
    tree = ContextTree()
    pose = Pose()
    old = Item("box", "object", "", pose, "a", 100, "a")
    new = Item("box", "object", "", Pose(1.0), "b", 200, "b")
    assert tree.merge(new)
    assert not tree.merge(old)  # older: ignored
    assert not tree.merge(new)  # the same version again: ignored
    assert tree.get("box").pose.x == 1.0
    # equal stamps: the greater writer name wins, on every robot
    tie = Item("box", "object", "", Pose(2.0), "c", 200, "c")
    assert tree.merge(tie)
    assert not tree.merge(Item("box", "object", "", Pose(3.0), "a", 200, "a"))
    # a removal is a tombstone: an older add arriving late does not resurrect the item
    assert tree.merge(Removal("box", 300, "a"))
    assert not tree.merge(Item("box", "object", "", pose, "z", 250, "z"))
    assert "box" not in tree
    assert tree.tombstones() == 1
    # a newer add does
    assert tree.merge(Item("box", "object", "", pose, "a", 400, "a"))
    assert "box" in tree
    assert tree.tombstones() == 0
    # a local change after a far-future remote one still wins (stamp above the held one)
    tree.merge(Item("far", "object", "", pose, "x", 10**15, "x"))
    local = tree.update(
        "far",
        kind=None,
        pose=Pose(5.0),
        maintainer=None,
        attributes_json=None,
        now_us=5,
        writer="me",
    )
    assert local.stamp_us == 10**15 + 1


def test_tombstones_expire() -> None:
    clock = ManualClock()
    manager = ContextManager("r1", clock=clock, tombstone_s=10.0)
    try:
        manager.add("a", "object")
        manager.remove("a")
        assert manager.removed("a") is not None
        tree = manager._tree  # no timer without a link: expire by hand
        clock.advance(11.0)
        assert tree.expire(clock.monotonic() - 10.0) == 1
        assert manager.removed("a") is None
    finally:
        manager.close()


def test_merged_conflicts_detach_instead_of_losing_items() -> None:
    tree = ContextTree()
    p = Pose()
    for name, stamp in (("map", 1), ("x", 2), ("y", 3)):
        tree.merge(Item(name, "object", "map" if name != "map" else "", p, "a", stamp, "a"))
    # another robot removed "map" while this one added a child under it
    tree.merge(Item("z", "object", "map", p, "b", 5, "b"))
    tree.merge(Removal("map", 6, "a"))
    assert [i.name for i in tree.detached()] == ["x", "y", "z"]
    with pytest.raises(ContextError, match="parent 'map' is not"):
        tree.world_pose("z")
    assert tree.subtree() == []
    # the parent comes back: they re-attach
    tree.merge(Item("map", "map", "", p, "b", 7, "b"))
    assert tree.detached() == []
    # concurrent re-parents closing a cycle: the oldest link of the cycle is cut
    tree.merge(Item("x", "object", "y", p, "a", 10, "a"))
    tree.merge(Item("y", "object", "x", p, "b", 11, "b"))
    assert [i.name for i in tree.detached()] == ["x"]
    assert [i.name for i in tree.subtree("x")] == ["x", "y"]
    assert [i.name for i in tree.subtree()] == ["map", "z"]
    with pytest.raises(ContextError, match="cycle"):
        tree.world_pose("y")
    # a newer change of the cut item moves the cut to the other, now older, member
    tree.merge(Item("x", "object", "y", Pose(1.0), "a", 12, "a"))
    assert [i.name for i in tree.detached()] == ["y"]
    # breaking the cycle re-attaches both
    tree.merge(Item("y", "object", "map", p, "a", 13, "a"))
    assert tree.detached() == []
    assert tree.path("x") == ["map", "y", "x"]


def test_pose_maths() -> None:
    a = Pose.from_euler(1.0, 2.0, 3.0, 0.1, -0.2, 0.3)
    assert a.euler() == pytest.approx((0.1, -0.2, 0.3))
    ident = a.compose(a.inverse())
    assert ident.as_tuple() == pytest.approx(Pose().as_tuple(), abs=1e-12)
    turn = Pose.from_euler(yaw=math.pi / 2)
    moved = turn.compose(Pose(1.0))
    assert (moved.x, moved.y) == pytest.approx((0.0, 1.0))
    assert Pose(0, 0, 0, 0, 0, 0, 2).qw == 1.0  # normalised
    assert Pose(0, 0, 0, 0, 0, 0, -1).qw == 1.0  # one sign
    with pytest.raises(ValueError, match="zero"):
        Pose(0, 0, 0, 0, 0, 0, 0)
    with pytest.raises(ValueError, match="finite"):
        Pose(math.inf)
    with pytest.raises(ValueError, match="numbers"):
        Pose("1")  # type: ignore[arg-type]


def test_closed_manager_refuses_changes() -> None:
    manager = ContextManager("r1")
    manager.add("a", "object")
    manager.close()
    manager.close()
    with pytest.raises(ContextError, match="closed"):
        manager.add("b", "object")
    assert manager.get("a").name == "a"
