"""Process per station, one supervisor: ``hookwatch run FLEET_DIR``.

- :mod:`.ipc` — the frames between supervisor and workers (length-prefixed JSON, bounded);
- :mod:`.worker` — one station in its own process (``python -m gateway.supervisor.worker``);
- :mod:`.supervisor` — starts, watches, restarts and reloads the workers; a :class:`StationHub`
  per station is where the supervisor's shared outputs (Modbus TCP, console, metrics) plug in;
- :mod:`.remote` — a :class:`~.remote.RemoteStation` per hub: the station proxy that rebuilds the
  station's records, events and state from the frames and drives the supervisor's shared outputs;
- :mod:`.fleetcfg` — a fleet folder read station by station (a broken file refuses one station).
"""
