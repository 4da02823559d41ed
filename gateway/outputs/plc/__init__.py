"""The PLC output: the register map (pure), the Modbus TCP output and its transport."""
