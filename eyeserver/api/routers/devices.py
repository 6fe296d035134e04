"""``/api/v1/devices``: the rig's devices and their health; a physicist changes their settings."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter, HTTPException
from starlette.concurrency import run_in_threadpool

from eyeserver.api.auth import PhysicistDep
from eyeserver.api.deps import ServiceDep
from eyeserver.api.schemas import DeviceResponse, DeviceSettingsRequest, ErrorResponse

__all__ = ["router"]

router = APIRouter(tags=["devices"])


@router.get("/devices", summary="List the devices")
async def list_devices(service: ServiceDep) -> list[DeviceResponse]:
    """Every device in opening order (projectors, cameras, trigger) with its health."""
    devices = await run_in_threadpool(service.devices)
    return [DeviceResponse.model_validate(asdict(d)) for d in devices]


@router.get("/devices/{device_id}", summary="One device",
            responses={404: {"model": ErrorResponse, "description": "No such device."}})
async def get_device(device_id: str, service: ServiceDep) -> DeviceResponse:
    """One device with its health and the driver's description."""
    try:
        device = await run_in_threadpool(service.device, device_id)
    except KeyError:
        raise HTTPException(404, f"no device with id {device_id!r}") from None
    return DeviceResponse.model_validate(asdict(device))


@router.patch("/devices/{device_id}", summary="Change a device's settings",
              responses={404: {"model": ErrorResponse, "description": "No such device."},
                         422: {"model": ErrorResponse, "description": "A setting that does "
                               "not apply to the device's kind, or a value out of range."},
                         503: {"model": ErrorResponse, "description": "The device failed, or "
                               "the acquisition queue is full."}})
async def configure_device(device_id: str, changes: DeviceSettingsRequest, service: ServiceDep,
                           caller: PhysicistDep) -> DeviceResponse:
    """Change a projector's ``enabled`` and ``intensity`` or a camera's ``exposure_us`` and
    ``gain_db`` (physicists only).

    The change waits for the captures queued before it, is applied all or nothing and is
    recorded in the audit log under the caller's name; the answer is the updated device.
    """
    try:
        device = await run_in_threadpool(service.configure_device, device_id,
                                         changes.model_dump(exclude_none=True),
                                         actor=caller.name)
    except KeyError:
        raise HTTPException(404, f"no device with id {device_id!r}") from None
    return DeviceResponse.model_validate(asdict(device))
