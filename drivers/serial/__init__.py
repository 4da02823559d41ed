"""The serial line shared by the drivers: tty set-up and the Modbus CRC."""
