"""What of a key expression a role of the secured network may read or publish: the access control's answer
(:data:`services.transport.security.ROLE_POLICIES`, the one place that says it) for a key expression that the role
may use only in part.

The router refuses a declaration that its rules do not wholly cover (a tablet subscribing to ``msk/<s>/**`` gets
nothing, not the activations it may read), and says so only in its trace log. :func:`permitted_parts` gives the
narrower key expressions the role may declare instead (``msk/<s>/activations/**``, ``msk/<s>/status/**``), so a tool
reads what it may and says what it may not (:meth:`services.nodes.node_runtime.NodeInputs.subscribe_readable`).
"""

from __future__ import annotations

import zenoh

from services.transport import topics
from services.transport.security import ROLE_POLICIES, refused


def permitted_parts(role: str | None, action: str, key_expr: str) -> tuple[str, ...]:
    """The key expressions within ``key_expr`` that ``role`` may ``action`` ("publish" or "subscribe"), together all
    it may of ``key_expr``: ``(key_expr,)`` when all of it (or without a role: no access control), ``()`` when none."""
    if role is None or refused(role, action, key_expr) is None:
        return (key_expr,)
    policy = ROLE_POLICIES.get(role)
    allowed = () if policy is None else (policy.publish if action == "publish" else policy.subscribe)
    parts: list[str] = []
    for granted in allowed:
        part = _common_part(key_expr, granted)
        if part is not None and part not in parts:
            parts.append(part)
    return tuple(parts)


def _common_part(wanted: str, granted: str) -> str | None:
    """The key expression matching exactly what both ``wanted`` and ``granted`` match, when it is one: chunk by chunk
    the more specific of the two, up to the first ``**`` (then the other's rest). None when they do not intersect or
    the common part is not one key expression of that form (checked: both must include it)."""
    wanted_ke, granted_ke = zenoh.KeyExpr(wanted), zenoh.KeyExpr(granted)
    if not wanted_ke.intersects(granted_ke):
        return None
    if wanted_ke.includes(granted_ke):
        return granted
    mine, theirs = wanted.split("/"), granted.split("/")
    chunks: list[str] = []
    for index, (a, b) in enumerate(zip(mine, theirs)):
        if a == "**" or b == "**":
            chunks += theirs[index:] if a == "**" else mine[index:]
            break
        chunks.append(b if a == "*" else a)
    else:
        longer = mine[len(theirs) :] or theirs[len(mine) :]
        if longer not in ([], ["**"]):
            return None
    candidate = "/".join(chunks)
    try:
        part = zenoh.KeyExpr(candidate)
    except Exception:  # zenoh's own error type: not a canonical key expression
        return None
    return candidate if wanted_ke.includes(part) and granted_ke.includes(part) else None


def parts_text(role: str, action: str, key_expr: str, parts: tuple[str, ...]) -> str:
    """One line: what ``role`` may ``action`` of ``key_expr`` (``parts``, :func:`permitted_parts`) and that the router
    refuses the rest; with no parts, the access control's own refusal (:func:`services.transport.security.refused`)."""
    if not parts:
        return refused(role, action, key_expr) or f"role {role!r} may {action} nothing of {key_expr}"
    verb = "read" if action == "subscribe" else action
    return f"role {role!r} may {verb} only {', '.join(parts)} of {key_expr}; the router refuses the rest"


def facts_refusal(role: str | None, session: str) -> str | None:
    """Why ``role`` may not publish session ``session``'s facts (its load key: loads and set marks); None when it may,
    or without a role. The router drops a put its access control refuses without a word, so what changes the facts
    (``msk load``, ``msk set``, the dashboard's set buttons, the view's keys) asks here first."""
    return None if role is None else refused(role, "publish", topics.load_key(session))
