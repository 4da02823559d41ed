"""Commissioning: ``hookwatch check --probe`` asks the installed hardware and services whether a
station can run (gateway/commission/probe.py)."""
