"""Offline tools: log analysis, log reading and its columnar companion, the history of
completed tests, campaign reports."""
