"""A small client of the coordinator's REST API (`/api/v1`), standard library only (urllib).

No bpy here: it runs in the submission's worker thread and in tests. Every failure becomes a
`PathfarmError` whose text is what the artist reads: the coordinator's own message for a 4xx
(`{"error": {"code", "message"}}`), and words for 401/403 and for a coordinator that cannot be
reached.
"""

import json
import ssl
import urllib.error
import urllib.request

API = "/api/v1"


class PathfarmError(Exception):
    """A failure worth showing to the artist as is."""

    def __init__(self, message, status=None, code=None):
        super().__init__(message)
        self.status = status
        self.code = code


def _explain(status, body):
    code = None
    message = None
    try:
        err = json.loads(body.decode("utf-8"))["error"]
        code, message = err.get("code"), err.get("message")
    except (ValueError, KeyError, TypeError, AttributeError):
        pass
    if status == 401:
        return PathfarmError(
            "The coordinator refused the client token (401): set the right token in the pathfarm "
            f"add-on's preferences ({message or 'unauthorized'}).",
            status,
            code,
        )
    if status == 403:
        return PathfarmError(
            f"The token is not a client token (403: {message or 'forbidden'}); use the coordinator's client token.",
            status,
            code,
        )
    text = message or body[:200].decode("utf-8", "replace").strip() or "no details"
    return PathfarmError(f"The coordinator answered {status}: {text}", status, code)


class Client:
    """`base`: the coordinator's URL (http:// or https://); `token`: the client token or None;
    `ca_file`: PEM certificates to trust for https besides the system's."""

    def __init__(self, base, token=None, ca_file=None, timeout=30.0):
        base = (base or "").strip().rstrip("/")
        if not base.startswith(("http://", "https://")):
            raise PathfarmError(f"The coordinator URL must start with http:// or https://, got {base!r}")
        self.base = base
        self.token = (token or "").strip() or None
        self.timeout = timeout
        self.context = None
        if base.startswith("https://"):
            try:
                self.context = ssl.create_default_context(cafile=ca_file or None)
            except (OSError, ssl.SSLError) as e:
                raise PathfarmError(f"Cannot read the CA file {ca_file!r}: {e}") from e

    def _request(self, method, path, body=None, content_type=None, accept="application/json"):
        req = urllib.request.Request(self.base + path, data=body, method=method)
        req.add_header("Accept", accept)
        if content_type:
            req.add_header("Content-Type", content_type)
        if self.token:
            req.add_header("Authorization", f"Bearer {self.token}")
        try:
            with urllib.request.urlopen(req, timeout=self.timeout, context=self.context) as resp:
                return resp.read()
        except urllib.error.HTTPError as e:
            raise _explain(e.code, e.read()) from None
        except (urllib.error.URLError, OSError) as e:
            reason = getattr(e, "reason", e)
            raise PathfarmError(f"Cannot reach the coordinator at {self.base}: {reason}") from None

    def _json(self, method, path, payload=None):
        body = None if payload is None else json.dumps(payload).encode("utf-8")
        data = self._request(method, path, body, "application/json" if body is not None else None)
        try:
            return json.loads(data.decode("utf-8")) if data else None
        except ValueError as e:
            raise PathfarmError(f"The coordinator's answer to {method} {path} is not JSON: {e}") from None

    def upload_scene(self, data):
        """`POST /scenes` with a .glb (or tar bundle): `{"scene_id", "triangles", "warnings"}`."""
        data = self._request("POST", API + "/scenes", data, "application/octet-stream")
        return json.loads(data.decode("utf-8"))

    def submit(self, job):
        """`POST /jobs`: the new job's id."""
        return self._json("POST", API + "/jobs", job)["id"]

    def job(self, job_id):
        return self._json("GET", f"{API}/jobs/{int(job_id)}")

    def cancel(self, job_id):
        return self._json("POST", f"{API}/jobs/{int(job_id)}/cancel")

    def frames(self, job_id):
        """`GET /jobs/{id}/frames`, every page: `[{"index", "frame", "state", "passes_done"}]`."""
        out, after = [], None
        while True:
            query = "?limit=1000" + (f"&after={after}" if after is not None else "")
            page = self._json("GET", f"{API}/jobs/{int(job_id)}/frames{query}")
            out.extend(page)
            if len(page) < 1000:
                return out
            after = page[-1]["index"]

    def frame_exr(self, job_id, frame):
        return self._request("GET", f"{API}/jobs/{int(job_id)}/frames/{int(frame)}/image.exr", accept="image/x-exr")

    def image_exr(self, job_id):
        return self._request("GET", f"{API}/jobs/{int(job_id)}/image.exr", accept="image/x-exr")

    def job_body_fields(self):
        """The fields `POST /jobs` accepts, from the coordinator's OpenAPI document: how the
        add-on learns which options (denoise, frame ranges...) this coordinator offers."""
        doc = self._json("GET", API + "/openapi.json")
        try:
            return set(doc["components"]["schemas"]["JobRequestBody"]["properties"])
        except (KeyError, TypeError):
            return set()

    def check(self):
        """Checks the URL and the token (a one-job page of `GET /jobs` needs a client token) and
        returns `job_body_fields()`."""
        fields = self.job_body_fields()
        self._json("GET", API + "/jobs?limit=1")
        return fields

    def dashboard_url(self, job_id=None):
        return self.base + "/" + (f"#job={int(job_id)}" if job_id is not None else "")
