"""YAML as the command line reads it: duplicate keys refused, alias expansion bounded.

PyYAML's ``safe_load`` keeps the last of two equal keys of a mapping without a word (a device
named twice under ``devices:`` lost the first), and expands aliases without a bound (an "alias
bomb" of 10^6 leaves in a few lines). :func:`safe_load_strict` refuses both with a
``yaml.YAMLError`` that has a position, so a caller's one-line YAML error applies.
"""

from __future__ import annotations

from typing import Any

import yaml
from yaml.composer import ComposerError
from yaml.constructor import ConstructorError
from yaml.nodes import MappingNode, Node, SequenceNode

__all__ = ["MAX_ALIASED_NODES", "safe_load_strict"]

#: The most nodes that aliases (``*name``) may add to one document, counted as if every alias
#: were a copy of what it names; a profile needs a handful, an alias bomb billions.
MAX_ALIASED_NODES = 10_000


class _StrictLoader(yaml.SafeLoader):
    """A safe loader that refuses duplicate keys and aliases adding too many nodes."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._aliased = 0
        self._sizes: dict[int, int] = {}

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()  # type: ignore[no-untyped-call]
            target = self.anchors.get(event.anchor)
            if target is not None:
                self._aliased += self._size(target)
                if self._aliased > MAX_ALIASED_NODES:
                    raise ComposerError(
                        None,
                        None,
                        f"aliases (*name) expand to more than {MAX_ALIASED_NODES} nodes",
                        event.start_mark,
                    )
        return super().compose_node(parent, index)

    def _size(self, node: Node) -> int:
        """How many nodes ``node`` stands for with every alias in it copied out."""
        known = self._sizes.get(id(node))
        if known is not None:
            return known
        self._sizes[id(node)] = MAX_ALIASED_NODES + 1  # a node inside itself: no end
        size = 1
        if isinstance(node, SequenceNode):
            size += sum(self._size(child) for child in node.value)
        elif isinstance(node, MappingNode):
            size += sum(self._size(k) + self._size(v) for k, v in node.value)
        size = min(size, MAX_ALIASED_NODES + 1)
        self._sizes[id(node)] = size
        return size

    def construct_mapping(self, node: MappingNode, deep: bool = False) -> Any:
        seen: set[object] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                duplicate = key in seen
                seen.add(key)
            except TypeError:  # an unhashable key: SafeConstructor reports it
                continue
            if duplicate:
                raise ConstructorError(
                    "while reading a mapping",
                    node.start_mark,
                    f"the key {key!r} is given twice (the first would be lost)",
                    key_node.start_mark,
                )
        return super().construct_mapping(node, deep=deep)


def safe_load_strict(text: str) -> Any:
    """``yaml.safe_load`` refusing duplicate keys and aliases that expand too far.

    Args:
        text: The YAML text.

    Returns:
        The document.

    Raises:
        yaml.YAMLError: Not YAML, a key given twice in one mapping, or aliases adding more
            than :data:`MAX_ALIASED_NODES` nodes (with the position of the problem).
    """
    loader = _StrictLoader(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()
