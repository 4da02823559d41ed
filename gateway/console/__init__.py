"""The operator console: web pages for the fleet, each station live and its history.

``server.ConsoleServer`` (aiohttp on its own thread and loop), ``feed`` (the bounded hand-over from
a station's slot loop and the min/max-decimated series), ``auth`` (users, sessions, CSRF, lockout).
"""
