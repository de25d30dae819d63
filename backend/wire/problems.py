"""Errors as RFC 9457 problem details: `application/problem+json` with type, title, status
and detail, plus `parameter` (what is at fault) and `fix` (what the client should change)."""

from __future__ import annotations

from http import HTTPStatus

from starlette.responses import JSONResponse

PROBLEM_JSON = "application/problem+json"
TYPE_PREFIX = "tag:scenesort,2026:"  # a tag URI (RFC 4151): an identifier, not a web page


class ApiError(Exception):
    """A refused request: HTTP `status`, the offending `parameter` and what would fix it.

    `headers` go on the response (Retry-After on 429/503)."""

    def __init__(
        self,
        status: int,
        parameter: str,
        message: str,
        fix: str,
        code: str = "invalid_request",
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.parameter = parameter
        self.message = message
        self.fix = fix
        self.code = code
        self.headers = headers or {}

    def to_json(self) -> dict[str, str | int]:
        """The problem document every error shares (`ErrorBody` in models.py)."""
        return {
            "type": TYPE_PREFIX + self.code,
            "title": HTTPStatus(self.status).phrase,
            "status": self.status,
            "detail": self.message,
            "parameter": self.parameter,
            "fix": self.fix,
        }

    def response(self) -> JSONResponse:
        return JSONResponse(
            self.to_json(), self.status, headers=self.headers, media_type=PROBLEM_JSON
        )


def busy(parameter: str, message: str, fix: str, retry_after_s: int = 1,
         status: int = 503, code: str = "busy") -> ApiError:
    """A 429/503 that tells the client when to try again."""
    return ApiError(status, parameter, message, fix, code, {"Retry-After": str(retry_after_s)})
