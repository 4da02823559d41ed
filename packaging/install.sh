#!/usr/bin/env bash
# hookwatch offline installer (inside the release tarball made by scripts/build-release).
#   ./install.sh                 install, or upgrade in place (configuration and records are kept)
#   ./install.sh --expect SHA256 install only the release whose manifest has this fingerprint
#                                (build-release prints it: the one that was signed off)
#   ./install.sh --uninstall     remove the software, units and rules; keep /etc/hookwatch and
#                                /var/lib/hookwatch (add --purge to remove those too)
#   --root DIR                   install into DIR as if it were / (a scratch root, an image)
# Needs no network and nothing but python3 and python3-venv. Every file of the release is checked
# against SHA256SUMS first; anything unlisted or changed refuses the install; a failure at any step
# changes nothing (the switch to the new version is the last step). docs/deploy.md §1.2.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
PY=${PYTHON:-python3}
action=install
args=()
while [ $# -gt 0 ]; do
  case "$1" in
    --root) [ $# -ge 2 ] || { echo "install.sh: --root needs a folder" >&2; exit 2; }
            args+=(--root "$2"); shift 2 ;;
    --expect) [ $# -ge 2 ] || { echo "install.sh: --expect needs the SHA-256 build-release printed" >&2; exit 2; }
            args+=(--expect "$2"); shift 2 ;;
    --uninstall) action=uninstall; shift ;;
    --purge) args+=(--purge); shift ;;
    -h|--help) sed -n '2,11p' "$0"; exit 0 ;;
    *) echo "install.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done
command -v "$PY" >/dev/null || { echo "hookwatch install: python3 is needed (Debian: apt-get install python3 python3-venv)" >&2; exit 1; }
# the installer proper (release.py) runs only as SHA256SUMS lists it; it checks everything else,
# the manifest first. -I -S -B: no site-packages, no .pth, no environment, no bytecode written here
sums=$(grep -E '^[0-9a-f]{64}  release\.py$' "$here/SHA256SUMS" 2>/dev/null) \
  || { echo "hookwatch install: refused: $here/SHA256SUMS does not list release.py: not a hookwatch release" >&2; exit 1; }
( cd "$here" && printf '%s\n' "$sums" | sha256sum --quiet --strict -c - >/dev/null 2>&1 ) \
  || { echo "hookwatch install: refused: release.py does not match its SHA-256 in SHA256SUMS: a damaged or changed copy" >&2; exit 1; }
if [ "$action" = install ]; then
  for a in "${args[@]}"; do [ "$a" = --purge ] && { echo "install.sh: --purge goes with --uninstall" >&2; exit 2; }; done
else
  for a in "${args[@]}"; do [ "$a" = --expect ] && { echo "install.sh: --expect goes with an install" >&2; exit 2; }; done
fi
exec "$PY" -I -S -B "$here/release.py" "$action" ${args[@]+"${args[@]}"}
