#!/usr/bin/env bash
# hookwatch offline installer (inside the release tarball made by scripts/build-release).
#   ./install.sh                 install, or upgrade in place (configuration and records are kept)
#   ./install.sh --uninstall     remove the software, units and rules; keep /etc/hookwatch and
#                                /var/lib/hookwatch (add --purge to remove those too)
#   --root DIR                   install into DIR as if it were / (a scratch root, an image)
# Needs no network: the venv is made from the bundled wheels only (pip --no-index).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
ROOT=/
action=install
purge=0
while [ $# -gt 0 ]; do
  case "$1" in
    --root) ROOT=$(realpath -m "$2"); shift 2 ;;
    --uninstall) action=uninstall; shift ;;
    --purge) purge=1; shift ;;
    -h|--help) sed -n '2,8p' "$0"; exit 0 ;;
    *) echo "install.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done
R=${ROOT%/}
OPT=$R/opt/hookwatch
ETC=$R/etc/hookwatch
MANIFEST=$OPT/MANIFEST
PY=${PYTHON:-python3}
live=0; [ "$R" = "" ] && live=1

say() { echo "hookwatch install: $*" >&2; }

put() {  # put MODE SRC DST: install a file the package owns (listed for uninstall)
  install -D -m "$1" "$2" "$3"
  echo "${3#"$R"}" >>"$MANIFEST.new"
}

if [ "$action" = uninstall ]; then
  [ -f "$MANIFEST" ] || { say "nothing installed under $R/ (no $MANIFEST)"; exit 1; }
  if [ $live = 1 ] && command -v systemctl >/dev/null 2>&1 && [ -d /run/systemd/system ]; then
    systemctl disable --now hookwatch-fleet.service 2>/dev/null || true
  fi
  while read -r f; do rm -f "$R$f"; done <"$MANIFEST"
  rm -rf "$OPT"
  if [ $purge = 1 ]; then
    rm -rf "$ETC" "$R/var/lib/hookwatch" "$R/var/log/hookwatch"
    say "removed, with the configuration and the records (--purge)"
  else
    say "removed; kept the configuration ($ETC) and the records ($R/var/lib/hookwatch)"
  fi
  [ $live = 1 ] && command -v systemctl >/dev/null 2>&1 && [ -d /run/systemd/system ] && systemctl daemon-reload || true
  exit 0
fi

command -v "$PY" >/dev/null || { say "python3 is needed (Debian: apt-get install python3 python3-venv)"; exit 1; }
want=$(cat "$here/VERSION")
( cd "$here/wheels" && sha256sum --quiet -c ../SHA256SUMS ) || { say "the wheels do not match SHA256SUMS: a damaged copy"; exit 1; }
mkdir -p "$OPT"
: >"$MANIFEST.new"
old=""
[ -x "$OPT/venv/bin/hookwatch" ] && old=$("$OPT/venv/bin/python" -c 'import importlib.metadata as m; print(m.version("hookwatch"))' 2>/dev/null || true)
# a new venv beside the old one, switched over (one symlink rename) only when it works: an upgrade
# that fails leaves the installed version as it was
new="venvs/$want-$(date +%Y%m%d%H%M%S)-$$"
mkdir -p "$OPT/venvs"
"$PY" -m venv "$OPT/$new" || { rm -rf "${OPT:?}/$new"; say "python3 -m venv failed (Debian: apt-get install python3-venv)"; exit 1; }
if ! "$OPT/$new/bin/python" -m pip install -q --no-index --find-links "$here/wheels" --disable-pip-version-check hookwatch \
   || ! "$OPT/$new/bin/hookwatch" --help >/dev/null; then
  rm -rf "${OPT:?}/$new"
  say "installing from the bundled wheels failed; the installed version is unchanged"; exit 1
fi
[ -e "$OPT/venv" ] && [ ! -L "$OPT/venv" ] && mv "$OPT/venv" "$OPT/venvs/pre-symlink-$$"
ln -sfn "$new" "$OPT/venv.tmp" && mv -T "$OPT/venv.tmp" "$OPT/venv"
for v in "$OPT"/venvs/*; do [ "$v" = "$OPT/$new" ] || rm -rf "$v"; done

d=$here/deploy
put 644 "$d/systemd/hookwatch-fleet.service" "$R/etc/systemd/system/hookwatch-fleet.service"
put 644 "$d/systemd/hookwatch@.service" "$R/etc/systemd/system/hookwatch@.service"
put 644 "$d/sysusers.d/hookwatch.conf" "$R/etc/sysusers.d/hookwatch.conf"
put 644 "$d/tmpfiles.d/hookwatch.conf" "$R/etc/tmpfiles.d/hookwatch.conf"
put 644 "$d/logrotate/hookwatch" "$R/etc/logrotate.d/hookwatch"
for f in "$d"/udev/*.rules; do put 644 "$f" "$R/etc/udev/rules.d/$(basename "$f")"; done
# examples and the simulator's scenarios, owned by the package
for f in $(cd "$here/config" && find . -type f); do put 644 "$here/config/$f" "$OPT/share/config/${f#./}"; done
# the configuration is the administrator's: written only where none is (an upgrade keeps it)
if [ ! -e "$ETC/fleet.yaml" ]; then
  install -D -m 644 "$here/config/fleet.yaml" "$ETC/fleet.yaml"
  mkdir -p "$ETC/stations" "$ETC/meters"
  cp -n "$here/config/meters/"*.yaml "$ETC/meters/"
  install -m 600 "$d/secrets.env.example" "$ETC/secrets.env"
  say "default configuration written to $ETC (add one stations/<id>.yaml per loom: docs/deploy.md)"
else
  say "configuration in $ETC kept"
fi
mv "$MANIFEST.new" "$MANIFEST"
echo "$want" >"$OPT/VERSION"

if [ $live = 1 ]; then
  command -v systemd-sysusers >/dev/null && systemd-sysusers /etc/sysusers.d/hookwatch.conf || true
  command -v systemd-tmpfiles >/dev/null && systemd-tmpfiles --create /etc/tmpfiles.d/hookwatch.conf || true
  if command -v systemctl >/dev/null && [ -d /run/systemd/system ]; then systemctl daemon-reload; fi
  command -v udevadm >/dev/null && udevadm control --reload 2>/dev/null || true
else
  command -v systemd-sysusers >/dev/null && systemd-sysusers --root="$R" "$R/etc/sysusers.d/hookwatch.conf" || true
  command -v systemd-tmpfiles >/dev/null && systemd-tmpfiles --root="$R" --create "$R/etc/tmpfiles.d/hookwatch.conf" || true
fi
if [ -n "$old" ]; then say "upgraded $old -> $want"; else say "installed $want under $OPT"; fi
