"""The STM32 take-up motor: its client over the wire, the exchange, the keep-alive and
the frames."""
