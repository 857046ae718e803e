"""FastAPI dependencies as Annotated aliases: settings, job manager, scene store, token."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.config import ServiceSettings
from service.manager import JobManager
from service.scenes import SceneStore

_bearer = HTTPBearer(auto_error=False, description="NPRT_API_TOKEN, when the server sets one")


def get_settings(request: Request) -> ServiceSettings:
    return request.app.state.settings


def get_manager(request: Request) -> JobManager:
    return request.app.state.manager


def get_scenes(request: Request) -> SceneStore:
    return request.app.state.scenes


SettingsDep = Annotated[ServiceSettings, Depends(get_settings)]
ManagerDep = Annotated[JobManager, Depends(get_manager)]
ScenesDep = Annotated[SceneStore, Depends(get_scenes)]


def require_token(settings: SettingsDep,
                  creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """Writing endpoints need `Authorization: Bearer <NPRT_API_TOKEN>` when a token is set."""
    if settings.api_token is None:
        return
    if creds is None:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "missing bearer token",
                            headers={"WWW-Authenticate": "Bearer"})
    if not hmac.compare_digest(creds.credentials.encode(), settings.api_token.encode()):
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "wrong bearer token",
                            headers={"WWW-Authenticate": "Bearer"})


TokenDep = Depends(require_token)
