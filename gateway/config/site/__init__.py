"""A site of many boxes (issue 37): the site repository (Git) and what a box does with it.

- :mod:`.repository` — the site repository: its boxes, a box's *effective tree* (the fleet folder
  the box runs: ``fleet.yaml``, ``stations/``, ``maps/``, ``site.yaml``), a commit read out of Git;
- :mod:`.sitecheck` — ``hookwatch config check``: the effective tree validated by the one station
  validation (:mod:`gateway.config.loader`, :mod:`gateway.config.checks`), errors mapped back to
  the repository's FILE:LINE; ``--site``: every box, station ids unique across the site;
- :mod:`.boxsettings` — the box's own settings (``/etc/hookwatch/box.yaml``): name, state folder,
  allowed signers, whether unsigned commits are allowed (a lab);
- :mod:`.versions` — the box's state folder: staged versions, the ``current`` symlink switched
  atomically, the last verified version, the journal, the repair of a half-applied version;
- :mod:`.signing` — an OpenSSH-signed commit (``git verify-commit``, ``gpg.format=ssh``);
- :mod:`.siteplan` — ``hookwatch config plan``: per station unchanged, apply-now, deferred, new,
  removed, with the changed keys (secrets masked);
- :mod:`.siteapply` — ``hookwatch config apply`` / ``rollback``: stage, switch, reload, health gate,
  rollback;
- :mod:`.boxreport` — the box's config report (what ``config status`` prints and the box's
  supervisor publishes).

The supervisor's side lives in gateway/supervisor/: ``boxagent.py`` (its pid and status files, the
repair at start, an apply killed half-way, drift, the deferral bookkeeping) and ``boxpublish.py``
(the retained report over MQTT, with a Will).
"""
