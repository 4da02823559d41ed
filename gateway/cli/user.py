"""`hookwatch user add|remove|list`: the people who may give commands from the operator console."""
from __future__ import annotations

import getpass
import grp
import os
import stat
import sys

from ..cli import CliError
from ..config import ConfigError, load_fleet, load_station
from ..outputs.console import auth

HELP = "manage the operator console's users (add, remove, list)"
DESCRIPTION = (HELP + ". Passwords are stored as salted scrypt hashes (N=2^14, r=8, p=1) in the "
               "users file: console.users_file of the station/fleet given, or --file.")


def add_arguments(ap):
    ap.add_argument("action", choices=("add", "remove", "list"))
    ap.add_argument("name", nargs="?", help="user name (add, remove)")
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--config", metavar="STATION.yaml|DIR", help="take console.users_file from this configuration")
    g.add_argument("--file", metavar="PATH", help="the users file")
    ap.add_argument("--password-stdin", action="store_true",
                    help="read the password from the first line of stdin (else asked twice on the terminal)")


def _users_file(args) -> str:
    if args.file:
        return args.file
    try:
        cfgs = load_fleet(args.config) if os.path.isdir(args.config) else [load_station(args.config)]
    except (ConfigError, FileNotFoundError) as e:
        raise CliError(str(e), 1) from None
    if not cfgs:
        raise CliError(f"{args.config}: no station files", 1)
    c = cfgs[0]
    return c.console.users_file or os.path.join(c.recorder.dir, "console-users.json")


#: the service's group (deploy/sysusers.d): the users file must be readable by it
SERVICE_GROUP = "hookwatch"


def share_with_service(path: str) -> str | None:
    """Make the users file readable by the service whoever ran the command: group = the service
    group where it exists, else the group of the folder the file is in (the service's state folder);
    mode 0640 (never world-readable: the file holds password hashes). Returns a warning or None."""
    gid: int | str = SERVICE_GROUP
    try:
        try:
            gid = grp.getgrnam(SERVICE_GROUP).gr_gid
        except KeyError:
            gid = os.stat(os.path.dirname(os.path.abspath(path))).st_gid
        st = os.stat(path)
        if st.st_gid != gid:
            os.chown(path, -1, gid)   # root may; a member of the group may; else PermissionError
        if stat.S_IMODE(st.st_mode) != 0o640:
            os.chmod(path, 0o640)
    except OSError as e:
        return (f"{path}: could not give it to group {gid} with mode 0640 "
                f"({e.strerror}); the service may not read it: chgrp {SERVICE_GROUP} {path}; chmod 640 {path}")
    return None


def run(args) -> int:

    path = _users_file(args)
    try:
        if args.action == "list":
            for name, e in sorted(auth.load_users(path).items()):
                print(f"{name}\tcreated {e.get('created', '?')}")
            return 0
        if not args.name:
            raise CliError(f"{args.action}: a user name is needed")
        if args.action == "remove":
            if not auth.remove_user(path, args.name):
                raise CliError(f"no user {args.name!r} in {path}", 1)
            warning = share_with_service(path)
            if warning:
                print(f"warning: {warning}", file=sys.stderr)
            print(f"user {args.name} removed from {path}")
            return 0
        if args.password_stdin:
            pw = sys.stdin.readline().rstrip("\n")
        else:
            pw = getpass.getpass(f"password for {args.name}: ")
            if getpass.getpass("again: ") != pw:
                raise CliError("the passwords differ", 1)
        new = auth.add_user(path, args.name, pw)
    except auth.UsersError as e:
        raise CliError(str(e), 1) from None
    warning = share_with_service(path)
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    print(f"user {args.name} {'added to' if new else 'updated in'} {path}")
    return 0
