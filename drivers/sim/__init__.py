"""Virtual twins of the station's devices (plant, ZN-S meter, STM32), for tests and commissioning."""
