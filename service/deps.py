"""FastAPI dependencies as Annotated aliases: settings, job API, scene store, token."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from nprt.service.auth import bearer_error
from nprt.service.config import ServiceSettings
from nprt.service.jobapi import JobApi
from nprt.service.scenes import SceneStore

_bearer = HTTPBearer(auto_error=False, description="NPRT_API_TOKEN, when the server sets one")

# Every dependency is `async def`: FastAPI runs a plain `def` one on a worker thread, and a
# thread hop per dependency costs more than the dependency itself, most of all under load.


async def get_settings(request: Request) -> ServiceSettings:
    return request.app.state.settings


async def get_api(request: Request) -> JobApi:
    return request.app.state.api


async def get_scenes(request: Request) -> SceneStore:
    return request.app.state.scenes


SettingsDep = Annotated[ServiceSettings, Depends(get_settings)]
ApiDep = Annotated[JobApi, Depends(get_api)]
ScenesDep = Annotated[SceneStore, Depends(get_scenes)]


async def require_token(settings: SettingsDep, request: Request,
                  _: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """Writing endpoints need `Authorization: Bearer <NPRT_API_TOKEN>` when a token is set.
    nprt.service.auth.TokenMiddleware enforces it before the body is read; this dependency
    declares the scheme in the OpenAPI schema and checks again."""
    if settings.api_token is None:
        return
    why = bearer_error(request.headers.get("authorization"), settings.api_token)
    if why is not None:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, why,
                            headers={"WWW-Authenticate": "Bearer"})


TokenDep = Depends(require_token)
