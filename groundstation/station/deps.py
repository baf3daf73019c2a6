"""Dependencies of the routers: the hub, the pusher, and the mapping of hub errors to HTTP."""
from __future__ import annotations

import json
from typing import Annotated

from fastapi import Depends, FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from groundstation.jsonsafe import jsonable
from groundstation.station.hub.session import ConflictError, NotFoundError, Session, SessionError
from groundstation.station.push import Pusher

__all__ = ["HubDep", "PusherDep", "get_hub", "get_pusher", "install_error_handlers"]


def get_hub(request: Request) -> Session:
    return request.app.state.hub


def get_pusher(request: Request) -> Pusher:
    return request.app.state.pusher


HubDep = Annotated[Session, Depends(get_hub)]
PusherDep = Annotated[Pusher, Depends(get_pusher)]

_STATUS = ((NotFoundError, 404), (ConflictError, 409), (SessionError, 400))


def install_error_handlers(app: FastAPI) -> None:
    """Hub errors become HTTP errors in one place: not found 404, wrong state 409, bad value 400."""
    async def handler(request: Request, exc: SessionError) -> JSONResponse:
        status = next(code for cls, code in _STATUS if isinstance(exc, cls))
        return JSONResponse({"detail": str(exc)}, status_code=status)

    app.add_exception_handler(SessionError, handler)
    app.add_exception_handler(RequestValidationError, validation_handler)


MAX_ECHOED_INPUT = 120   # characters of a rejected value shown back in a 422


async def validation_handler(request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 with FastAPI's usual detail list, but a long input is not echoed back whole, and a
    non-finite number in it (NaN, Infinity, 1e400) is shown as null (JSON has no such numbers)."""
    errors = jsonable(jsonable_encoder(exc.errors(), custom_encoder={Exception: str, bytes: repr}))
    for error in errors:
        shown = json.dumps(error.get("input"))
        if len(shown) > MAX_ECHOED_INPUT:
            error["input"] = f"{shown[:MAX_ECHOED_INPUT]}... ({len(shown)} characters)"
    return JSONResponse({"detail": errors}, status_code=422)
