"""The ``"pipeline"`` server: components composed by a template, made by the Component Manager.

:class:`PipelineServer` loads a :class:`~temoto.managers.component.messages.PipelineRequest`
as one ``"component"`` resource per segment of its template (registrar dependencies, requested
producer first, wired by channels the manager allocates), fails the pipeline when a segment
fails for good, and after a restart keeps it only if every segment survived. See
``docs/component-manager.md``.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from temoto.core.registrar import LoadContext, ResourceInfo, ResourceServer, Status
from temoto.errors import ComponentNotFoundError, ResourceError
from temoto.managers.component.messages import ComponentRequest, PipelineRequest, PipelineResponse

if TYPE_CHECKING:
    from temoto.core.registrar import Registrar
    from temoto.managers.component.description import PipelineTemplate

__all__ = ["PipelineHost", "PipelineServer"]

logger = logging.getLogger(__name__)


class PipelineHost(Protocol):
    """What the pipeline server needs of the Component Manager that made it."""

    @property
    def name(self) -> str:
        """The manager's server name: the segments are requested from it."""

    @property
    def registrar(self) -> Registrar:
        """The registrar both servers serve on."""

    def template(self, name: str) -> PipelineTemplate:
        """A pipeline template by name (ComponentNotFoundError if unknown)."""

    def check_type(self, type: str, *, name: str = "", local_only: bool = False) -> None:  # noqa: A002
        """Raise ComponentNotFoundError unless some candidate can provide the type now."""

    def channel(self, uid: str, output: str) -> str:
        """The channel the manager allocates to one output (or link) of a resource."""


class PipelineServer(ResourceServer[PipelineRequest, PipelineResponse]):
    """The ``"pipeline"`` server: components composed by a template (made by the manager).

    Each segment is a ``"component"`` resource requested while the pipeline loads, so it is a
    registrar dependency: released with the pipeline, and its statuses (WARNING on a
    failover, FATAL when no substitute is left) reach the pipeline's consumers. Links are
    channels the manager allocates; a substitute segment is started on the same channels,
    which is how the pipeline is re-wired without restarting the other segments.

    Args:
        manager: The Component Manager.
    """

    name: ClassVar[str] = "pipeline"
    request_type: ClassVar[type[Any]] = PipelineRequest
    response_type: ClassVar[type[Any]] = PipelineResponse

    def __init__(self, manager: PipelineHost) -> None:
        self.manager = manager

    def on_load(self, request: PipelineRequest, ctx: LoadContext) -> PipelineResponse:
        """Check every segment's type, then request the segments producer first."""
        manager = self.manager
        template = manager.template(request.template)
        order = template.order()
        for seg in order:  # every type first: nothing is started for a request that cannot be
            try:
                manager.check_type(seg.type, local_only=request.local_only)
            except ComponentNotFoundError as err:
                raise ComponentNotFoundError(
                    f"template '{template.name}' segment '{seg.name}': {err}",
                    origin=manager.registrar.name,
                ) from None
        pinned = dict(request.outputs)
        unknown = set(pinned) - {n for n, _ in template.outputs}
        if unknown:
            raise ComponentNotFoundError(
                f"template '{template.name}' has no output(s) {', '.join(sorted(unknown))}",
                origin=manager.registrar.name,
            )
        links: dict[str, str] = {}
        for out, link in template.outputs:
            links[link] = pinned.get(out) or manager.channel(ctx.resource_id, link)
        for seg in order:
            for _, link in seg.inputs:
                links.setdefault(link, manager.channel(ctx.resource_id, link))
        segments = []
        for seg in order:
            outputs = {
                link.partition(".")[2]: ch
                for link, ch in links.items()
                if link.partition(".")[0] == seg.name
            }
            inputs = {inp: links[link] for inp, link in seg.inputs}
            component = ComponentRequest(
                seg.type,
                outputs=tuple(outputs.items()),
                inputs=tuple(inputs.items()),
                parameters=seg.parameters,
                local_only=request.local_only,
                failover=request.failover,
            )
            res = manager.registrar.call(manager.name, component)  # a dependency
            segments.append((seg.name, res.resource_id))
        return PipelineResponse(
            template.name,
            tuple((out, links[link]) for out, link in template.outputs),
            tuple(segments),
            tuple(sorted(links.items())),
        )

    def on_unload(self, request: PipelineRequest, response: PipelineResponse) -> None:
        """Nothing: the segments are dependencies, released by the registrar."""

    def on_status(self, resource: ResourceInfo, status: Status, message: str) -> None:
        """A segment failed for good (FATAL): the pipeline is failed too.

        Its consumers already got the segment's FATAL; marking the pipeline failed keeps new
        equal requests from sharing a pipeline with a dead segment (they load a fresh one).

        Args:
            resource: The pipeline.
            status: The status (of the pipeline or, up the chain, of a segment).
            message: What happened.
        """
        if status is Status.FATAL and not resource.failed:
            try:
                self.manager.registrar.send_status(
                    resource.id, Status.FATAL, f"a segment failed: {message}"
                )
            except ResourceError as err:
                logger.debug("pipeline %s is gone: %s", resource.id, err)

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        """After a restart: the pipeline is live only if every segment still is.

        The registrar asks the segments (components) first; one that is gone or failed makes
        the pipeline FATAL, so that it is never shared with nothing behind it.

        Args:
            resource: A restored pipeline.

        Returns:
            None if every segment is live (or the pipeline had failed before), else FATAL.
        """
        if resource.failed:
            return None
        response = resource.response
        registrar = self.manager.registrar
        for segment, uid in response.segments:
            try:
                failed = registrar.info(uid).failed
            except ResourceError:
                failed = True
            if failed:
                return (
                    Status.FATAL,
                    f"pipeline '{response.template}': segment '{segment}' did not survive the"
                    " restart; request the pipeline again",
                )
        return None
