"""Own Modbus TCP transport in layers (no pymodbus on the server side): the MBAP framer
(:mod:`.framer`), the pure PDU codec and register reads (:mod:`.pdu`), and the asyncio server with
connection caps, idle timeout, pacing and rate-limited logging (:mod:`.server`)."""
