"""Errors that end a command with one clear line (never a traceback)."""


class SlamError(Exception):
    """Base class: the command-line layer prints ``str(err)`` on one line and exits non-zero."""


class DataError(SlamError):
    """Bad input data: missing or unreadable file, inconsistent folder, bad calibration.

    The message names the file and the problem, e.g.
    ``"/data/seq/video_frames/000012l.png: cannot read image"``.
    """


class ConfigError(SlamError):
    """Bad configuration: unknown key, wrong type, value out of range."""


def one_line(err: BaseException, limit: int = 300) -> str:
    """An exception as one line for a table or a log line: our errors by their message, others
    with their type named."""
    text = " ".join(str(err).split())
    return (text if isinstance(err, SlamError) else f"{type(err).__name__}: {text}")[:limit]
