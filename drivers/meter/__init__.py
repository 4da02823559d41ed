"""The tension meter: a generic Modbus RTU meter driven by a register map file
(config/meters/*.yaml)."""
