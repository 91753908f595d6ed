"""A Foxglove layout for a robot's live channels and displays (``--foxglove-layout FILE``).

Built with the SDK's own layout types (``foxglove.layouts``, the importable form of Foxglove's
layout format, https://docs.foxglove.dev/docs/visualization/layouts), so the file is what the
app imports (*Layouts* → *Import from file*). The panels follow the robot's features:

* navigation: a 3D panel (the ``/tf`` frames and ``/<robot>/pose``);
* manipulation: a Plot of each joint's position (``/<robot>/joint_states.position[i]``);
* flight: a Map following ``/<robot>/location``;
* always: the robot's health (Raw Messages), the node transitions (State Transitions of
  ``/temoto/transitions.new``) and the log (``/temoto/log``);
* one Raw Messages panel per display given (``/display/<name>/<field>``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from temoto.errors import ConfigError
from temoto.managers.visualization.foxglove import import_foxglove
from temoto.managers.visualization.messages import DisplayRequest

__all__ = ["robot_layout", "write_layout"]


def robot_layout(
    robot: str = "",
    features: Sequence[str] = (),
    joints: Sequence[str] = (),
    displays: Sequence[DisplayRequest] = (),
) -> str:
    """A layout as JSON text.

    Args:
        robot: The robot's name ("" = no robot panels).
        features: Its features (``navigation``, ``manipulation``, ``flight``).
        joints: The arm's joints in profile order (the Plot's series).
        displays: Displays to give a panel each.

    Returns:
        The layout (JSON).

    Raises:
        ConfigError: The SDK is missing (the message names the extra).
    """
    import_foxglove()
    import foxglove.layouts as fl

    views: list[Any] = []
    if robot and "navigation" in features:
        views.append(fl.ThreeDeePanel(title=f"{robot}: odometry"))
    if robot and "manipulation" in features and joints:
        series = [
            fl.PlotSeries(value=f"/{robot}/joint_states.position[{i}]", label=joint)
            for i, joint in enumerate(joints)
        ]
        views.append(
            fl.PlotPanel(title=f"{robot}: joints (rad)", config=fl.PlotConfig(paths=series))
        )
    if robot and "flight" in features:
        views.append(
            fl.MapPanel(
                title=f"{robot}: location", config=fl.MapConfig(follow_topic=f"/{robot}/location")
            )
        )
    for display in displays:
        views.append(
            fl.RawMessagesPanel(
                title=f"display {display.name}",
                config=fl.RawMessagesConfig(topic_path=display.topic),
            )
        )
    status: list[Any] = []
    if robot:
        status.append(
            fl.RawMessagesPanel(
                title=f"{robot}: health", config=fl.RawMessagesConfig(topic_path=f"/{robot}/health")
            )
        )
    status.append(
        fl.StateTransitionsPanel(
            title="node states",
            config=fl.StateTransitionsConfig(
                paths=[fl.StateTransitionsSeries(value="/temoto/transitions.new", label="new")]
            ),
        )
    )
    status.append(fl.LogPanel(title="log", config=fl.LogConfig(topic_to_render="/temoto/log")))
    rows = (
        [
            fl.SplitItem(
                content=fl.SplitContainer(
                    direction="row", items=[fl.SplitItem(content=p) for p in views]
                )
            )
        ]
        if views
        else []
    )
    rows.append(
        fl.SplitItem(
            content=fl.SplitContainer(
                direction="row", items=[fl.SplitItem(content=p) for p in status]
            )
        )
    )
    layout = fl.Layout(content=fl.SplitContainer(direction="column", items=rows))
    return str(layout.to_json())


def write_layout(path: str | Path, text: str) -> None:
    """Write a layout file.

    Raises:
        ConfigError: It cannot be written (the message names it).
    """
    try:
        Path(path).write_text(text + "\n", encoding="utf-8")
    except OSError as err:
        raise ConfigError(
            f"{path}: cannot write the Foxglove layout: {err.strerror or err}"
        ) from None
