"""A finished run's status: a result, an untrusted result, or not a result (``metrics.json``'s
``status``; ``slam run`` exits 3 for a run that is not a result, 0 for the others)."""
from __future__ import annotations

#: a finished run whose failed share is above this is not a result (``slam run`` exits 3)
MAX_FAILED_SHARE = 0.5
#: a finished run whose flagged share is above this is untrusted (a result, its figures marked)
MAX_FLAGGED_SHARE = 0.5
#: how the status of a run that is not a result begins
NOT_A_RESULT = "not a result"


def run_status(frames: int, failed: int, flagged: int = 0) -> str:
    """``ok``; ``not a result: N of M frames failed`` when more than :data:`MAX_FAILED_SHARE` of
    the processed frames failed (their poses are carried over, not tracked); else ``untrusted: N
    of M frames flagged`` when more than :data:`MAX_FLAGGED_SHARE` were flagged (their poses are
    results, but uncertain or contradicted)."""
    if frames > 0 and failed > MAX_FAILED_SHARE * frames:
        return f"{NOT_A_RESULT}: {failed} of {frames} frames failed"
    if frames > 0 and flagged > MAX_FLAGGED_SHARE * frames:
        return f"untrusted: {flagged} of {frames} frames flagged"
    return "ok"


def is_result(status: str) -> bool:
    """Whether a run of ``status`` (:func:`run_status`) is a result (``ok`` or untrusted)."""
    return not status.startswith(NOT_A_RESULT)
