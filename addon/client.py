"""HTTP client of the scenesort service, standard library only.

No proxy is used (http.client connects directly: the service is local, a system proxy
must not see or break the traffic), and every call has a timeout. Errors become
`ServiceError` with a message a user understands; the service's own JSON error
(`message`, `fix`) is passed on. The token of a service this add-on started goes with every request.
"""

from __future__ import annotations

import hashlib
import http.client
import json
import threading
import urllib.parse
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from .service import token_for
from .tasks import Cancelled

HEALTH_TIMEOUT_S = 2.0  # health and HEAD are cheap: fail fast when nothing listens
UPLOAD_TIMEOUT_S = 60.0
UPLOAD_CHUNK = 4 * 2**20  # an upload asks whether to stop after each of these
# Build and render answer only when done; this bounds the silence between bytes.
WORK_TIMEOUT_S = 900.0
SCENE_HASH_CHARS = 32  # backend/wire/binary.py keeps 32 hex characters of the sha256
LOGGED_REQUESTS = 1000  # `Client.requests` keeps at least the last this many


class ServiceError(Exception):
    """A failed request, in words for the user; `status` is the HTTP status or None."""

    def __init__(self, message: str, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status


# A request body: whole, or as blocks sent one after another (a scene's arrays, not joined)
Body = bytes | Sequence[memoryview]


def _blocks(body: Body) -> Sequence[bytes | memoryview]:
    return [body] if isinstance(body, bytes) else body


def _length(body: Body) -> int:
    return sum(memoryview(block).nbytes for block in _blocks(body))


def scene_id(vertex_count: int, triangle_count: int, body: Body) -> str:
    """The service's content id of a scene upload (same rule as backend/wire/binary.py)."""
    digest = hashlib.sha256(b"scenesort-scene-v1 %d %d\n" % (vertex_count, triangle_count))
    for block in _blocks(body):
        digest.update(block)
    return digest.hexdigest()[:SCENE_HASH_CHARS]


def instances_id(mesh_count: int, instance_count: int, body: bytes) -> str:
    """The service's content id of an instance list (same rule as backend/wire/binary.py)."""
    digest = hashlib.sha256(b"scenesort-instances-v1 %d %d\n" % (mesh_count, instance_count))
    digest.update(body)
    return digest.hexdigest()[:SCENE_HASH_CHARS]


def _chunks(body: Body, stop: Callable[[], bool]) -> Iterator[memoryview]:
    """`body` in pieces of at most UPLOAD_CHUNK, raising Cancelled (which ends the
    request: the service sees the body cut short and keeps nothing) before a piece once
    `stop()`."""
    for block in _blocks(body):
        view = memoryview(block).cast("B")
        for start in range(0, len(view), UPLOAD_CHUNK):
            if stop():
                raise Cancelled()
            yield view[start:start + UPLOAD_CHUNK]


def _error_text(status: int, reason: str, payload: bytes) -> str:
    """The service's error message (and its suggested fix) from an error response."""
    try:
        data = json.loads(payload or b"{}")
    except ValueError:
        data = {}
    if isinstance(data, dict):
        detail = data.get("detail")
        if isinstance(detail, str):  # a problem document (RFC 9457): detail, and our fix
            fix = data.get("fix")
            return f"{detail} ({fix})" if isinstance(fix, str) else detail
        if isinstance(detail, list) and detail and isinstance(detail[0], dict):
            return str(detail[0].get("msg", detail[0]))
    return reason or f"HTTP {status}"


# The server closed a kept-alive connection while it was idle: the request never reached it.
_STALE = (http.client.RemoteDisconnected, ConnectionResetError, BrokenPipeError)


class Client:
    """Calls on one service base URL, e.g. http://127.0.0.1:8765, over kept-alive
    connections (a new TCP connection per call costs ~1.5 ms: a viewport round makes ten)."""

    def __init__(self, base_url: str, token: str | None = None) -> None:
        """`token` defaults to that of the service this add-on started at `base_url`."""
        url = base_url.strip().rstrip("/")
        parts = urllib.parse.urlsplit(url)
        if parts.scheme not in {"http", "https"} or not parts.hostname:
            raise ServiceError(f"'{base_url}' is not a service URL like http://127.0.0.1:8765")
        self.base_url = url
        self.token = token if token is not None else token_for(url)
        self.requests: list[str] = []  # "METHOD path" of every request made, for the panel
        self._parts = parts
        self._idle: list[http.client.HTTPConnection] = []  # kept alive between calls
        self._lock = threading.Lock()  # calls from several threads each take their own

    def close(self) -> None:
        """Close the kept connections (a later call opens a new one)."""
        with self._lock:
            idle, self._idle = self._idle, []
        for connection in idle:
            connection.close()

    def _exchange(self, method: str, path: str, body: Body | None, headers: dict[str, str],
                  timeout: float, stop: Callable[[], bool] | None,
                  ) -> tuple[int, str, dict[str, str], bytes]:
        """One request and its whole answer, on a kept connection if one is idle. One
        that the server closed while idle (no byte of the request reached it) is
        replaced once."""
        with self._lock:
            kept = self._idle.pop() if self._idle else None
        try:
            return self._once(kept or self._new(), method, path, body, headers, timeout, stop)
        except _STALE:
            if kept is None:
                raise
            return self._once(self._new(), method, path, body, headers, timeout, stop)

    def _new(self) -> http.client.HTTPConnection:
        kind = (http.client.HTTPSConnection if self._parts.scheme == "https"
                else http.client.HTTPConnection)
        return kind(self._parts.hostname, self._parts.port)

    def _once(self, connection: http.client.HTTPConnection, method: str, path: str,
              body: Body | None, headers: dict[str, str], timeout: float,
              stop: Callable[[], bool] | None) -> tuple[int, str, dict[str, str], bytes]:
        connection.timeout = timeout
        if connection.sock is not None:
            connection.sock.settimeout(timeout)
        data: Any = body if stop is None or body is None else _chunks(body, stop)
        try:
            connection.request(method, self._parts.path + path, data, headers)
            response = connection.getresponse()
            payload = response.read()
        except BaseException:
            connection.close()  # a request cut short leaves the connection unusable
            raise
        if response.will_close:
            connection.close()
        else:
            with self._lock:
                self._idle.append(connection)
        return response.status, response.reason, dict(response.getheaders()), payload

    def _request(
        self,
        method: str,
        path: str,
        body: Body | None = None,
        content_type: str | None = None,
        timeout: float = HEALTH_TIMEOUT_S,
        stop: Callable[[], bool] | None = None,
    ) -> tuple[int, dict[str, str], bytes]:
        headers = {} if body is None else {"Content-Length": str(_length(body))}
        if content_type:
            headers["Content-Type"] = content_type
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        self.requests.append(f"{method} {path.split('?')[0]}")
        if len(self.requests) > 2 * LOGGED_REQUESTS:  # a viewport's client lives for hours
            del self.requests[:-LOGGED_REQUESTS]
        try:
            status, reason, head, payload = self._exchange(method, path, body, headers,
                                                           timeout, stop)
        except TimeoutError:
            raise ServiceError(
                f"The service at {self.base_url} did not answer within {timeout:g} s"
            ) from None
        except ConnectionRefusedError:
            raise ServiceError(
                f"No scenesort service is running at {self.base_url}: "
                "press 'Start local service' or check the URL"
            ) from None
        except (http.client.HTTPException, OSError) as exc:
            raise ServiceError(f"The connection to {self.base_url} failed: {exc}") from None
        if status == 404 and method == "HEAD":
            return 404, {}, b""
        if status >= 400:
            verb = "failed on" if status >= 500 else "refused"
            raise ServiceError(f"The service {verb} {method} {path.split('?')[0]}: "
                               f"{_error_text(status, reason, payload)}", status)
        return status, head, payload

    def _json(
        self, method: str, path: str, payload: Any = None, timeout: float = HEALTH_TIMEOUT_S
    ) -> dict:
        body = None if payload is None else json.dumps(payload).encode()
        _, _, data = self._request(
            method, path, body, "application/json" if body else None, timeout
        )
        try:
            return json.loads(data)
        except ValueError:
            raise ServiceError(f"The service sent an unreadable answer to {path}") from None

    def health(self) -> dict:
        """`GET /v1/health`: version, Warp version, device, cache use."""
        return self._json("GET", "/v1/health")

    def has_scene(self, scene_id: str) -> bool:
        """`HEAD /v1/scenes/{id}`: whether the service already holds this scene."""
        status, _, _ = self._request("HEAD", f"/v1/scenes/{scene_id}", timeout=HEALTH_TIMEOUT_S)
        return status == 200

    def upload_scene(self, vertex_count: int, triangle_count: int, body: Body,
                     blocks: dict[str, str] | None = None,
                     stop: Callable[[], bool] | None = None) -> dict:
        """`POST /v1/scenes`: the raw scene body, with `blocks` the flags of its optional
        blocks (`SceneMesh.query()`); returns scene_id, triangles, bounds, ... `stop`:
        asked between chunks of the body; True ends the upload (Cancelled)."""
        query = urllib.parse.urlencode(
            {"vertices": vertex_count, "triangles": triangle_count, **(blocks or {})})
        _, _, data = self._request(
            "POST", f"/v1/scenes?{query}", body, "application/octet-stream", UPLOAD_TIMEOUT_S,
            stop,
        )
        return json.loads(data)

    def has_mesh(self, mesh_id: str) -> bool:
        """`HEAD /v1/meshes/{id}`: whether the service already holds this mesh."""
        status, _, _ = self._request("HEAD", f"/v1/meshes/{mesh_id}", timeout=HEALTH_TIMEOUT_S)
        return status == 200

    def put_mesh(self, mesh_id: str, vertex_count: int, triangle_count: int, body: Body,
                 blocks: dict[str, str] | None = None,
                 stop: Callable[[], bool] | None = None) -> dict:
        """`PUT /v1/meshes/{id}`: one mesh of an instance list, in its own space (`stop`:
        as `upload_scene`'s)."""
        query = urllib.parse.urlencode(
            {"vertices": vertex_count, "triangles": triangle_count, **(blocks or {})})
        _, _, data = self._request(
            "PUT", f"/v1/meshes/{mesh_id}?{query}", body, "application/octet-stream",
            UPLOAD_TIMEOUT_S, stop,
        )
        return json.loads(data)

    def upload_instances(self, mesh_count: int, instance_count: int, body: bytes,
                         visibility: bool = False) -> dict:
        """`POST /v1/instance-scenes`: an instance list over meshes the service holds
        (`visibility`: the body ends with the instances' ray visibility masks)."""
        fields = {"meshes": mesh_count, "instances": instance_count}
        query = urllib.parse.urlencode({**fields, **({"visibility": "true"} if visibility
                                                     else {})})
        _, _, data = self._request(
            "POST", f"/v1/instance-scenes?{query}", body, "application/octet-stream",
            UPLOAD_TIMEOUT_S,
        )
        return json.loads(data)

    def build_bvh(self, scene_id: str, method: str, leaf_size: int) -> dict:
        """`POST /v1/scenes/{id}/bvh`: timings_ms (total and per phase) and statistics."""
        return self._json(
            "POST",
            f"/v1/scenes/{scene_id}/bvh",
            {"method": method, "leaf_size": int(leaf_size)},
            timeout=WORK_TIMEOUT_S,
        )

    # --- jobs: long renders from a camera description, with progress and cancel ---

    def create_job(self, payload: dict[str, Any]) -> dict:
        """`POST /v1/jobs`: queue an AO render of a camera (see camera.camera_dict)."""
        return self._json("POST", "/v1/jobs", payload, timeout=UPLOAD_TIMEOUT_S)

    def create_surface_job(self, scene_id: str, points: int, body: bytes,
                           settings: dict[str, Any]) -> dict:
        """`POST /v1/scenes/{id}/surface-jobs`: queue AO at `points` surface points (a
        bake's texels: P int32 triangles, P float32 u, P float32 v)."""
        query = urllib.parse.urlencode({"points": points, **settings})
        _, _, data = self._request(
            "POST", f"/v1/scenes/{scene_id}/surface-jobs?{query}", body,
            "application/octet-stream", UPLOAD_TIMEOUT_S,
        )
        return json.loads(data)

    def job_status(self, job_id: str, wait: float = 0.0) -> dict:
        """`GET /v1/jobs/{id}`: state, phase, progress (0..1), timings; with `wait`, as
        soon as the job ends or after `wait` seconds."""
        query = f"?wait={wait:g}" if wait > 0.0 else ""
        return self._json("GET", f"/v1/jobs/{job_id}{query}", timeout=UPLOAD_TIMEOUT_S)

    def cancel_job(self, job_id: str) -> dict:
        """`DELETE /v1/jobs/{id}`: the service stops the job at its next step."""
        return self._json("DELETE", f"/v1/jobs/{job_id}", timeout=UPLOAD_TIMEOUT_S)

    def job_result(self, job_id: str, pixels: int, layer: str = "f32") -> np.ndarray:
        """`GET /v1/jobs/{id}/result?format=...` (f32, coverage, depth, holdout, normal,
        position, object, triangle): `pixels` float32 values (pixels times the layer's
        channels), row 0 at the top."""
        _, _, data = self._request(
            "GET", f"/v1/jobs/{job_id}/result?format={layer}", timeout=UPLOAD_TIMEOUT_S
        )
        if len(data) != 4 * pixels:
            raise ServiceError(
                f"The service sent {len(data)} bytes for {pixels} pixels; expected {4 * pixels}"
            )
        return np.frombuffer(data, dtype="<f4").astype(np.float32)
