"""Bearer tokens with roles: viewer < operator < engineer (``auth.tokens`` in the configuration).

- Reads (``GET`` under ``/api``) need a viewer token, unless ``auth.anonymous_read`` is true.
- Target writes (post a batch, cancel, requeue) need an operator token.
- Data sets, fits, models and diagnoses need an engineer token for every write.
- ``/health``, ``/ready`` and the dashboard's static files need no token; ``/metrics`` needs none
  while ``auth.anonymous_metrics`` is true (the default), otherwise a viewer token.

A missing or unknown token is answered 401 with ``WWW-Authenticate: Bearer``; a known token
whose role is too low, 403. Tokens are compared in constant time.
"""

from __future__ import annotations

import hmac
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Annotated, Literal

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from comp_daemon.service.config import AuthSettings, Role

__all__ = ["ANONYMOUS", "AuthError", "Principal", "TokenTable", "require"]


@dataclass(frozen=True, slots=True)
class Principal:
    """Who made a request: the token's configured name and role."""

    name: str
    role: Role


ANONYMOUS = Principal("anonymous", Role.viewer)


class AuthError(Exception):
    """401 (``status`` 401, no or unknown token) or 403 (role too low)."""

    def __init__(self, status: int, message: str) -> None:
        self.status = status
        self.message = message
        super().__init__(message)


class TokenTable:
    """The configured tokens; :meth:`identify` maps a presented token to its principal."""

    def __init__(self, settings: AuthSettings) -> None:
        self._entries = [(t.secret.encode(), Principal(t.name, t.role_level)) for t in settings.tokens]
        self.anonymous_read = settings.anonymous_read
        self.anonymous_metrics = settings.anonymous_metrics

    def identify(self, presented: str) -> Principal | None:
        given = presented.encode()
        found = None
        for secret, principal in self._entries:  # no early exit: time does not depend on the match
            if hmac.compare_digest(secret, given):
                found = principal
        return found

    def authorize(self, presented: str | None, needed: Role, *, anonymous_ok: bool = False) -> Principal:
        if presented is None:
            if anonymous_ok:
                return ANONYMOUS
            raise AuthError(401, "a bearer token is required (Authorization: Bearer <token>)")
        principal = self.identify(presented)
        if principal is None:
            raise AuthError(401, "unknown token")
        if principal.role < needed:
            raise AuthError(
                403, f"this needs the {needed.name} role; token '{principal.name}' is {principal.role.name}"
            )
        return principal


_bearer = HTTPBearer(auto_error=False, description="A token from the daemon's configuration (auth.tokens)")


def require(
    role: Role,
    *,
    read: bool = False,
    anonymous_if: Literal["anonymous_read", "anonymous_metrics"] | None = None,
) -> Callable[..., Awaitable[Principal]]:
    """A FastAPI dependency that admits requests carrying a token of at least ``role``.

    An anonymous request is admitted as a viewer when the ``auth`` setting named by ``anonymous_if``
    is on; ``read=True`` is short for ``anonymous_if="anonymous_read"``.
    """
    flag = anonymous_if if anonymous_if is not None else ("anonymous_read" if read else None)

    async def dependency(
        request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
    ) -> Principal:
        table: TokenTable = request.app.state.tokens
        presented = credentials.credentials if credentials is not None else None
        if presented is None and request.headers.get("authorization"):
            raise AuthError(401, "the Authorization header must be 'Bearer <token>'")
        anonymous_ok = flag is not None and bool(getattr(table, flag))
        return table.authorize(presented, role, anonymous_ok=anonymous_ok)

    return dependency
