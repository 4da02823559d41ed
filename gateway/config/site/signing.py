"""A version is a Git commit signed with an OpenSSH key the box trusts.

``git verify-commit`` with ``gpg.format=ssh`` and ``gpg.ssh.allowedSignersFile`` set to the box's
``allowed_signers`` (ssh-keygen's ALLOWED SIGNERS format: ``principal namespaces="git" ssh-ed25519
AAAA…``). Git runs ``ssh-keygen -Y find-principals`` and ``-Y verify`` itself; an unsigned commit,
a signature by a key not in the file, or a file that does not exist is refused — unless the box's
own settings allow unsigned commits (a lab), which is said in the journal and the report.
"""
from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass

__all__ = ["Verdict", "verify_commit"]


@dataclass(frozen=True)
class Verdict:
    ok: bool
    signed: bool
    why: str          # the signer (ok) or the refusal


def _run(root: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["git", "-C", root, *args], capture_output=True, text=True, timeout=60,
                          stdin=subprocess.DEVNULL, errors="replace")


def verify_commit(root: str, sha: str, allowed_signers: str) -> Verdict:
    """Whether commit ``sha`` of the repository at ``root`` is signed by an allowed signer."""
    try:
        raw = _run(root, "cat-file", "commit", sha)
    except (OSError, subprocess.TimeoutExpired) as e:
        return Verdict(False, False, f"git: {e}")
    if raw.returncode != 0:
        return Verdict(False, False, f"{sha[:12]}: not a commit")
    header = raw.stdout.split("\n\n", 1)[0]
    if "\ngpgsig " not in "\n" + header:
        return Verdict(False, False, f"commit {sha[:12]} is not signed")
    if not os.path.isfile(allowed_signers):
        return Verdict(False, True, f"no allowed signers file {allowed_signers}: no key is trusted")
    try:
        p = _run(root, "-c", "gpg.format=ssh", "-c", f"gpg.ssh.allowedSignersFile={allowed_signers}",
                 "verify-commit", "--raw", sha)
    except (OSError, subprocess.TimeoutExpired) as e:
        return Verdict(False, True, f"git verify-commit: {e}")
    text = " ".join((p.stderr or p.stdout).split())[:300]
    if p.returncode != 0:
        return Verdict(False, True, f"commit {sha[:12]}: signature not by an allowed signer ({text})")
    return Verdict(True, True, text or "good signature")
