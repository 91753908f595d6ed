"""The consumers' side of the Component Manager: :class:`ComponentManagerClient`.

An action (or any consumer) asks for a component type or a pipeline; it gets a handle whose
channels stay the same across failovers (a substitute publishes where the consumer listens).
Bad requests fail here, before the registrar is called, with the typed error itself
(:class:`~temoto.errors.ComponentNotFoundError`, :class:`~temoto.errors.PipelineError`);
through ``registrar.call`` the same errors arrive chained inside ``ResourceLoadError``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from temoto.core.registrar import Registrar, Resource, StatusUpdate
from temoto.errors import ComponentNotFoundError
from temoto.managers._client import find_manager, registrar_of
from temoto.managers.component.manager import ComponentManager
from temoto.managers.component.messages import (
    ComponentRequest,
    ComponentResponse,
    PipelineRequest,
    PipelineResponse,
)

if TYPE_CHECKING:
    from temoto.core.action import Action

__all__ = ["ComponentHandle", "ComponentManagerClient", "PipelineHandle"]


class ComponentHandle:
    """A consumer's component: its reference and its current candidate.

    Args:
        registrar: The registrar.
        resource: The consumer's reference.
    """

    def __init__(self, registrar: Registrar, resource: Resource[Any]) -> None:
        self.registrar = registrar
        self.resource = resource

    @property
    def response(self) -> ComponentResponse:
        """The current response (the active candidate; it changes on failover)."""
        response = self.registrar.info(self.resource.resource_id).response
        assert isinstance(response, ComponentResponse)
        return response

    @property
    def name(self) -> str:
        """The active candidate's name."""
        return self.response.name

    def channel(self, output: str = "") -> str:
        """Where an output arrives (stable across failovers).

        Args:
            output: The output's name ("" = the first).

        Returns:
            The channel.
        """
        return self.response.output(output)


class PipelineHandle:
    """A consumer's pipeline.

    Args:
        registrar: The registrar.
        resource: The consumer's reference.
    """

    def __init__(self, registrar: Registrar, resource: Resource[Any]) -> None:
        self.registrar = registrar
        self.resource = resource

    @property
    def response(self) -> PipelineResponse:
        """The pipeline's response."""
        response = self.resource.response
        assert isinstance(response, PipelineResponse)
        return response

    def channel(self, output: str = "") -> str:
        """Where a pipeline output arrives.

        Args:
            output: The output's name ("" = the first).

        Returns:
            The channel.
        """
        return self.response.output(output)

    def segments(self) -> dict[str, ComponentResponse]:
        """Each segment's current candidate.

        Returns:
            Segment name -> the response of its component resource.
        """
        return {seg: self.registrar.info(uid).response for seg, uid in self.response.segments}


class ComponentManagerClient:
    """Finds the Component Manager on a registrar and hands out components and pipelines.

    Args:
        registrar: The registrar the Component Manager serves on.

    Raises:
        ResourceNotFoundError: No Component Manager serves there.
    """

    def __init__(self, registrar: Registrar) -> None:
        self.registrar = registrar
        self.manager = find_manager(registrar, ComponentManager, "Component Manager")

    @classmethod
    def for_action(cls, action: Action) -> ComponentManagerClient:
        """The client on the registrar of the engine running ``action``.

        Raises:
            ResourceNotFoundError: The engine has no registrar, or no Component Manager.
        """
        return cls(registrar_of(action))

    def component_request(
        self,
        type: str,  # noqa: A002
        *,
        name: str = "",
        outputs: Mapping[str, str] | None = None,
        inputs: Mapping[str, str] | None = None,
        parameters: Mapping[str, str] | None = None,
        local_only: bool = False,
        failover: bool = True,
    ) -> ComponentRequest:
        """Build and check a request (the type must have an available candidate).

        Raises:
            ComponentNotFoundError: No candidate can provide the type.
            TypeError: A bad field.
            ValueError: A bad channel.
        """
        request = ComponentRequest(
            type,
            name=name,
            outputs=tuple((outputs or {}).items()),
            inputs=tuple((inputs or {}).items()),
            parameters=tuple((parameters or {}).items()),
            local_only=local_only,
            failover=failover,
        )
        self.manager.check_type(type, name=name, local_only=local_only)
        return request

    def request(
        self,
        type: str,  # noqa: A002
        *,
        client: str = "",
        on_status: Callable[[StatusUpdate], None] | None = None,
        **options: Any,
    ) -> ComponentHandle:
        """Request a component outside an action (release ``handle.resource.id`` when done).

        Args:
            type: The component type.
            client: Who holds it.
            on_status: Called with its statuses (WARNING on failover, FATAL when none left).
            **options: ``name``, ``outputs``, ``inputs``, ``parameters``, ``local_only``,
                ``failover`` (see :class:`ComponentRequest`).

        Returns:
            The handle.

        Raises:
            ComponentNotFoundError: No candidate can provide the type.
            ResourceLoadError: No candidate could start.
        """
        request = self.component_request(type, **options)
        resource = self.registrar.call(
            ComponentManager.name, request, client=client, on_status=on_status
        )
        return ComponentHandle(self.registrar, resource)

    def acquire(self, action: Action, type: str, **options: Any) -> ComponentHandle:  # noqa: A002
        """Request a component for an action (released when its graph run ends).

        Args:
            action: The action.
            type: The component type.
            **options: As for :meth:`request`.

        Returns:
            The handle.
        """
        request = self.component_request(type, **options)
        return ComponentHandle(self.registrar, action.acquire(ComponentManager.name, request))

    def pipeline_request(
        self,
        template: str,
        *,
        outputs: Mapping[str, str] | None = None,
        local_only: bool = False,
        failover: bool = True,
    ) -> PipelineRequest:
        """Build and check a pipeline request (template known, every segment type available).

        Raises:
            ComponentNotFoundError: Unknown template, or a segment type with no candidate.
        """
        request = PipelineRequest(
            template,
            outputs=tuple((outputs or {}).items()),
            local_only=local_only,
            failover=failover,
        )
        tpl = self.manager.template(template)
        for seg in tpl.order():
            try:
                self.manager.check_type(seg.type, local_only=local_only)
            except ComponentNotFoundError as err:
                raise ComponentNotFoundError(
                    f"template '{template}' segment '{seg.name}': {err}",
                    origin=self.registrar.name,
                ) from None
        return request

    def request_pipeline(
        self,
        template: str,
        *,
        client: str = "",
        on_status: Callable[[StatusUpdate], None] | None = None,
        **options: Any,
    ) -> PipelineHandle:
        """Request a pipeline outside an action.

        Args:
            template: The template's name.
            client: Who holds it.
            on_status: Called with its statuses (and its segments').
            **options: ``outputs``, ``local_only``, ``failover``.

        Returns:
            The handle.
        """
        request = self.pipeline_request(template, **options)
        resource = self.registrar.call("pipeline", request, client=client, on_status=on_status)
        return PipelineHandle(self.registrar, resource)

    def acquire_pipeline(self, action: Action, template: str, **options: Any) -> PipelineHandle:
        """Request a pipeline for an action (released when its graph run ends).

        Args:
            action: The action.
            template: The template's name.
            **options: As for :meth:`request_pipeline`.

        Returns:
            The handle.
        """
        request = self.pipeline_request(template, **options)
        return PipelineHandle(self.registrar, action.acquire("pipeline", request))

    def release(self, handle: ComponentHandle | PipelineHandle) -> bool:
        """Release a handle taken with :meth:`request` or :meth:`request_pipeline`.

        Returns:
            True if the resource was unloaded.
        """
        return self.registrar.release(handle.resource.id)
