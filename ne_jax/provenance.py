"""Where a result came from: the git commit of the checkout and what was modified in it, for the
results files the experiments write (every table names the commit, the config key and the command)."""

from __future__ import annotations

import subprocess
from pathlib import Path

_REPO = Path(__file__).resolve().parent.parent


def _run(*args: str) -> str | None:
    try:
        return subprocess.run(["git", *args], capture_output=True, text=True, check=True, cwd=_REPO).stdout
    except (OSError, subprocess.CalledProcessError):
        return None


def git(*args: str) -> str:
    """``git *args`` run in the checkout that holds this package (stdout, stripped), or
    ``"unknown"`` where there is no git or no checkout."""
    out = _run(*args)
    return "unknown" if out is None else out.strip()


def commit(short: bool = False) -> str:
    """The checkout's ``HEAD`` commit (abbreviated with ``short``), or ``"unknown"``."""
    return git("rev-parse", *(["--short"] if short else []), "HEAD")


def modified(*paths: str) -> list[str]:
    """Tracked files (under ``paths``, default all) that differ from ``HEAD`` in the work tree."""
    out = _run("status", "--porcelain", "--untracked-files=no", "--", *paths) or ""
    return [line[3:] for line in out.splitlines() if line.strip()]


__all__ = ["commit", "git", "modified"]
