"""The operator console: web pages for the fleet, each station live and its history.

``app.ConsoleServer`` (aiohttp on its own thread and loop: the app and its lifecycle), its route
modules by subject (``routes_fleet``, ``routes_session``, ``routes_station``, ``routes_campaign``)
sharing one ``context.ConsoleContext``, ``feed`` (the bounded hand-over from a station's slot loop
and the min/max-decimated series), ``auth`` (users, sessions, CSRF, lockout).
"""
