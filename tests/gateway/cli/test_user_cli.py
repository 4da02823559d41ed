"""`hookwatch user add` as root leaves a users file the unprivileged service can read."""
from __future__ import annotations

import os
import pwd
import shutil
import stat
import subprocess
import tempfile

import pytest

from conftest import hookwatch_cmd


def _as_nobody(argv):
    setpriv = shutil.which("setpriv")
    assert setpriv, "setpriv (util-linux) is part of every Debian"
    nobody = pwd.getpwnam("nobody")
    return subprocess.run([setpriv, f"--reuid={nobody.pw_uid}", f"--regid={nobody.pw_gid}", "--clear-groups",
                           *argv], capture_output=True, text=True, timeout=30)


@pytest.fixture
def open_tmp():
    """A folder others may traverse (pytest's tmp_path lives below a 0700 folder of root's)."""
    d = tempfile.mkdtemp(prefix="hookwatch-users-")
    os.chmod(d, 0o755)
    yield d
    shutil.rmtree(d, ignore_errors=True)


def test_user_add_as_root_is_readable_by_the_service_group(open_tmp):
    if os.geteuid() != 0:
        pytest.skip("the case is root writing a file for the service user")
    nobody = pwd.getpwnam("nobody")
    state = os.path.join(open_tmp, "state")
    os.mkdir(state)
    # the service's state folder: root-owned, group of the service (here nobody's group), 0750
    os.chown(state, 0, nobody.pw_gid)
    os.chmod(state, 0o750)
    users = os.path.join(state, "console-users.json")
    r = subprocess.run([*hookwatch_cmd(), "user", "add", "operator", "--file", str(users), "--password-stdin"],
                       input="correct horse battery\n", capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    st = os.stat(users)
    assert stat.S_IMODE(st.st_mode) == 0o640
    assert st.st_gid == nobody.pw_gid
    # the service (a member of that group only) reads it; nobody else could
    r = _as_nobody(["cat", str(users)])
    assert r.returncode == 0 and "operator" in r.stdout, r.stderr
    # removing a user keeps it readable
    r = subprocess.run([*hookwatch_cmd(), "user", "remove", "operator", "--file", str(users)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert _as_nobody(["cat", str(users)]).returncode == 0
