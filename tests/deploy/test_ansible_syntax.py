"""deploy/ansible/ as ansible-playbook reads it (issue 37 item 8): both playbooks and the role
parse against the example inventory, and release.yml refuses to start without a release and its
fingerprint (the running rollouts are tests/deploy/test_ansible_site.py)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
import yaml

from kit.site_lab import ANSIBLE_DIR, ansible_playbook


def _run(tmp_path, *args):
    env = dict(os.environ, ANSIBLE_HOME=str(tmp_path / "ansible-home"), ANSIBLE_NOCOLOR="1",
               ANSIBLE_CONFIG=os.path.join(ANSIBLE_DIR, "ansible.cfg"))
    return subprocess.run([ansible_playbook(), *args], cwd=ANSIBLE_DIR, capture_output=True, text=True,
                          timeout=300, env=env)


@pytest.mark.parametrize("playbook", ["site.yml", "release.yml"])
def test_the_playbooks_parse(tmp_path, playbook):
    r = _run(tmp_path, "-i", "inventory.example.yml", playbook, "--syntax-check")
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"playbook: {playbook}" in r.stdout


def test_release_needs_the_tarball_and_its_fingerprint(tmp_path):
    inv = tmp_path / "inventory.yml"
    inv.write_text(yaml.safe_dump({"hookwatch_boxes": {"hosts": {"box-1": {}}, "vars": {
        "ansible_connection": "local", "ansible_python_interpreter": sys.executable}}}))
    r = _run(tmp_path, "-i", str(inv), "release.yml", "-e", "hookwatch_release_tarball=/nonexistent.tar.gz")
    assert r.returncode != 0
    assert "give -e hookwatch_release_tarball=PATH -e hookwatch_release_fingerprint=SHA256" in r.stdout, r.stdout
    assert "Install it" not in r.stdout
