"""The shared test kit: processes, broker, virtual devices, fakes (see tests/conftest.py)."""
