"""The pure core: contracts, records, the command rules and intake, alarms, control, the slot
window, validation and the method. No I/O, no clock, no threads (tests/test_architecture.py)."""
