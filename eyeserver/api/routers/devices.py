"""``GET /api/v1/devices`` and ``GET /api/v1/devices/{id}``: the rig's devices and their health."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter, HTTPException
from starlette.concurrency import run_in_threadpool

from eyeserver.api.deps import ServiceDep
from eyeserver.api.schemas import DeviceResponse, ErrorResponse

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
