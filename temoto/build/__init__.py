"""Actions and graphs written in Python: the short way to the same UMRF graphs.

Three layers, each usable alone:

* :func:`action` declares an action's inputs and outputs on the class (or turns a plain function
  into an action), so no separate ``*.umrf.json`` description is needed; :func:`catalog` puts
  such actions into an :class:`~temoto.core.catalog.ActionCatalog` for an engine.
* :func:`sequence`, :func:`parallel` and :func:`branch` compose steps (actions, :func:`node`
  leaves with literal values, other compositions) and :func:`graph` turns them into an
  :class:`~temoto.core.graph.UmrfGraph`::

      @action(outputs={"text": str})
      def hello():
          return {"text": "hello"}

      @action(inputs={"text": str}, outputs={"text": str})
      def shout(text):
          return {"text": text.upper() + "!"}

      with ActionEngine(actions=catalog(hello, shout)) as engine:
          print(engine.run(graph(hello, shout)).outputs)  # {'text': 'HELLO!'}

* :class:`GraphBuilder` adds nodes and links them one by one, for what compositions cannot say
  (cycles, reactive sources, conditions of any kind, non-required parents).

Every node gets its action's parameters from the action's description (the decorator's, or the
catalog's for an action named by a string), with the literal values given for it. The builders
write the graph as a UMRF document and parse it with :func:`~temoto.core.graph.parse_graph`, so
a graph built here is the graph its JSON would be (:meth:`GraphBuilder.document` gives that
JSON), checked by the same parser with the same messages. ``docs/python-api.md`` is the guide.
"""

from __future__ import annotations

from temoto.build._actions import (
    ActionDecorator,
    Param,
    ParamDecl,
    action,
    catalog,
    description_of,
)
from temoto.build._builder import ActionRef, GraphBuilder, Node
from temoto.build._flows import (
    Flow,
    Leaf,
    Step,
    branch,
    graph,
    graph_builder,
    graph_document,
    node,
    parallel,
    sequence,
)

__all__ = [
    "ActionDecorator",
    "ActionRef",
    "Flow",
    "GraphBuilder",
    "Leaf",
    "Node",
    "Param",
    "ParamDecl",
    "Step",
    "action",
    "branch",
    "catalog",
    "description_of",
    "graph",
    "graph_builder",
    "graph_document",
    "node",
    "parallel",
    "sequence",
]
