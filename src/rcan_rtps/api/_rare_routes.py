"""REST handlers an idle bridge is rarely asked for: HiTL review, audit reads, camera
images, thoughts and the skill list. Loaded by the first request to any of them (`_app`
registers them through `_lazy.on_first_request`): no stop or command runs them (issue 27:
idle memory). The routes a command, a stop or a status read takes are in `_routes`.
"""

from __future__ import annotations

import msgspec
from aiohttp import web

from rcan_rtps.governance import Governor, Principal, Rejection
from rcan_rtps.governance.hitl import Verdict
from rcan_rtps.rcan import Authorize, ErrorCode, PendingAuth, Role, SchemaValidationError

from ._approvals import readable
from ._bodies import (
    ApiError,
    AuditPage,
    PendingList,
    PendingView,
    error_body,
    error_response,
    json_response,
)
from ._commands import decode_as, schema_failure, too_large
from ._errors import AuditUnreadable, ReadsBusy
from ._images import REFUSALS, frame_headers, image_list
from ._keys import CHECKS, GOVERNOR, IMAGES, INVOCATIONS, PRINCIPAL, READS, SETTINGS
from ._routes import read_body
from .ports import ImageFrame, ImageSource, ImageUnavailable


def _forbidden(request: web.Request, needed: Role) -> web.Response | None:
    """Reads are not commands: a refusal here is answered 403 but not audited."""
    if request[PRINCIPAL].role >= needed:
        return None
    return error_response(403, ErrorCode.INSUFFICIENT_PRIVILEGES,
                          reason=f"needs {needed.name} or higher")


async def get_thought(request: web.Request) -> web.Response:
    """§16.5: any authenticated principal (status scope); `reasoning` for OWNER+ only. The
    record of the first principal to name the id, or of `?principal=` (another who did)."""
    thought = request.app[GOVERNOR].thoughts.read(request.match_info["thought_id"],
                                                   request[PRINCIPAL],
                                                   request.query.get("principal"))
    if thought is None:
        return error_response(404, "NOT_FOUND", reason="thought_not_found")
    return json_response(thought)


async def get_skills(request: web.Request) -> web.Response:
    """The skills an INVOKE may name (RCAN §18/§19.7), any principal: a client must not invoke
    an unlisted skill, and the conformance runner picks one to invoke from here."""
    return json_response(request.app[INVOCATIONS].invocations().listed(request.app[GOVERNOR]))


async def get_images(request: web.Request) -> web.Response:
    return json_response(image_list(request.app[IMAGES].names()))


async def image_reply(images: ImageSource, name: str
                      ) -> tuple[int, ImageFrame | ApiError]:
    try:
        return 200, await images.frame(name)
    except ImageUnavailable as exc:
        status, code = REFUSALS[exc.reason]
        return status, error_body(code, reason=exc.reason, outcome="failed")


async def get_image(request: web.Request) -> web.Response:
    status, frame = await image_reply(request.app[IMAGES], request.match_info["name"])
    if isinstance(frame, ApiError):
        return json_response(frame, status)
    return web.Response(body=frame.data, content_type=frame.mime,
                        headers=frame_headers(frame))


# -- HiTL -----------------------------------------------------------------------------------


async def get_pending(request: web.Request) -> web.Response:
    """The held commands, for those who could approve one: those the caller could approve,
    and its own (`readable`); `?mine=true`: the caller's own, for any principal (an agent
    that waits on several)."""
    governor, principal = request.app[GOVERNOR], request[PRINCIPAL]
    mine = request.query.get("mine")
    if mine not in (None, "true", "false"):
        return error_response(400, ErrorCode.SCHEMA_VALIDATION_FAILED,
                              reason="expected true or false", path="$.query.mine")
    if mine != "true":
        refused = _forbidden(request, request.app[SETTINGS].hitl_list_role)
        if refused is not None:
            return refused
    await governor.expire_pending()  # what has timed out is gone, and audited as such
    return json_response(PendingList(pending=own_pending(governor, principal)
                                     if mine == "true" else readable(principal,
                                                                     governor.pending())))


def own_pending(governor: Governor, principal: Principal) -> list[PendingAuth]:
    return [p for p in governor.pending() if p.issued_by == principal.name]


async def pending_view(governor: Governor, principal: Principal, pending_id: str
                       ) -> tuple[int, PendingView | ApiError]:
    """One held command, for its issuer (an agent waiting for a human) and its approvers:
    waiting, or what came of it. Anyone else is refused as if it were unknown (404)."""
    await governor.expire_pending()  # an expired one reads as expired, not as waiting
    record = governor.pending_record(pending_id)
    if record is None or not record.may_read(principal):
        return 404, error_body("NOT_FOUND", reason="pending_not_found")
    decision = record.decision
    return 200, PendingView(pending_id=record.held.pending_id, state=record.state,
                            pending=record.held,
                            decision=decision.body() if decision else None)


async def get_pending_one(request: web.Request) -> web.Response:
    status, body = await pending_view(request.app[GOVERNOR], request[PRINCIPAL],
                                      request.match_info["pending_id"])
    return json_response(body, status)


async def post_authorize(request: web.Request) -> web.Response:
    return await _resolve(request, "approve")


async def post_deny(request: web.Request) -> web.Response:
    return await _resolve(request, "deny")


async def post_withdraw(request: web.Request) -> web.Response:
    """The issuer takes its pending command back (approvers may too); others get 403."""
    return await _resolve(request, "withdraw")


async def _resolve(request: web.Request, verdict: Verdict) -> web.Response:
    governor, principal = request.app[GOVERNOR], request[PRINCIPAL]
    raw = await read_body(request)
    if raw is None:
        status, body = await too_large(governor, principal)
        return json_response(body, status)
    try:
        target: Authorize = decode_as(raw, Authorize)
    except SchemaValidationError as exc:
        status, body = await schema_failure(governor, principal, exc.path, exc.detail)
        return json_response(body, status)
    refused = _unsigned_refusal(request, verdict)
    if refused is not None:  # (audited as the desk audits its refusals, by pending_id)
        decision = await governor.refuse_review(target.pending_id, principal, verdict, refused)
        return json_response(decision.body(), decision.http_status)
    # The governor checks who may review it, and audits either way (with the reason).
    review = {"approve": governor.authorize, "deny": governor.deny,
              "withdraw": governor.withdraw}[verdict]
    decision = await review(target.pending_id, principal, target.reason)
    return json_response(decision.body(), decision.http_status)


def _unsigned_refusal(request: web.Request, verdict: Verdict) -> Rejection | None:
    """These bodies carry no signature: an approval by a principal whose policy is
    `required` is refused (SIGNATURE_REQUIRED `unsigned`; it sends a signed AUTHORIZE to
    /api/command or the WebSocket instead). Denials and withdrawals pass."""
    signatures = request.app[CHECKS].signatures
    if signatures is None:
        return None
    refusal, _ = signatures.check_review(request[PRINCIPAL].name, verdict == "approve", None)
    return refusal


# -- audit ----------------------------------------------------------------------------------


def _query_int(request: web.Request, name: str, default: int, lo: int, hi: int) -> int:
    text = request.query.get(name)
    if text is None:
        return default
    if not (text.isascii() and text.isdigit()) or len(text) > 18 or not lo <= int(text) <= hi:
        raise SchemaValidationError(f"$.query.{name}", f"expected an integer in [{lo}, {hi}]")
    return int(text)


def _paging(request: web.Request) -> tuple[int, int]:
    """`since` and `limit` of an audit page (raises SchemaValidationError)."""
    page_max = request.app[SETTINGS].audit_page_max
    return (_query_int(request, "since", 0, 0, 2**62),
            _query_int(request, "limit", page_max, 1, page_max))


def _page_body(app: web.Application, lines: list[bytes], since: int) -> bytes:
    """An AuditPage with the entries passed on byte for byte, so a client can re-hash and
    re-verify each."""
    from ._reads import line_seq  # loaded by the first audit read, as the readers are

    last = line_seq(lines[-1]) if lines else since
    page = AuditPage(entries=[], next_since=last, head_seq=app[GOVERNOR].audit.head.last_seq)
    head = msgspec.json.encode(page)
    return head.replace(b'"entries":[]', b'"entries":[' + b",".join(lines) + b"]", 1)


_READS_BUSY = (429, error_body(ErrorCode.RATE_LIMITED, reason="reads_busy"))
_UNREADABLE = (503, error_body("AUDIT_UNREADABLE", reason=AuditUnreadable.REASON))


def _refusal(status: int, body: ApiError) -> web.Response:
    """A read's refusal: busy (429) says when to come back, an unreadable log does not."""
    return json_response(body, status, {"Retry-After": "1"} if status == 429 else None)


async def get_audit(request: web.Request) -> web.Response:
    refused = _forbidden(request, request.app[SETTINGS].audit_read_role)
    if refused is not None:
        return refused
    try:
        since, limit = _paging(request)
    except SchemaValidationError as exc:
        return error_response(400, ErrorCode.SCHEMA_VALIDATION_FAILED, reason=exc.detail,
                              path=exc.path)
    try:
        lines = await request.app[READS].get().page(since, limit)
        if lines is None:  # the reader is busy: a bound, not a fault; try again shortly
            return _refusal(*_READS_BUSY)
        return web.Response(body=_page_body(request.app, lines, since),
                            content_type="application/json")
    except AuditUnreadable:
        return _refusal(*_UNREADABLE)


async def my_audit(app: web.Application, principal: Principal, since: int, limit: int,
                   last: bool) -> tuple[int, bytes | ApiError]:
    """The caller's own entries (any role: what it did, never anyone else's)."""
    from ._reads import entries_of

    try:
        reads = app[READS].get()
        lines = await reads.read(entries_of, app[GOVERNOR].audit.path, principal.name, since,
                                 limit, last, reads.page_bytes)
        return 200, _page_body(app, lines, since)
    except ReadsBusy:
        return _READS_BUSY
    except AuditUnreadable:
        return _UNREADABLE


async def get_my_audit(request: web.Request) -> web.Response:
    """GET /api/audit/mine?since=&limit= (oldest first) or ?last=N (the newest N)."""
    try:
        since, limit = _paging(request)
        last = _query_int(request, "last", 0, 0, request.app[SETTINGS].audit_page_max)
    except SchemaValidationError as exc:
        return error_response(400, ErrorCode.SCHEMA_VALIDATION_FAILED, reason=exc.detail,
                              path=exc.path)
    status, body = await my_audit(request.app, request[PRINCIPAL], since, last or limit,
                                  last > 0)
    if isinstance(body, bytes):
        return web.Response(body=body, content_type="application/json")
    return _refusal(status, body)


async def get_audit_verify(request: web.Request) -> web.Response:
    """Coalesced with concurrent requests, run in a worker process (see `_reads`)."""
    refused = _forbidden(request, request.app[SETTINGS].audit_read_role)
    if refused is not None:
        return refused
    return json_response(await request.app[READS].get().verify())
