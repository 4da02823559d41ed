"""Northbound interfaces: MQTT (with an on-disk outbox) and a Modbus TCP server for PLCs.

One definition each of the MQTT schema (mqtt_schema.py) and the register map (registers.py) feeds the
runtime, the generated docs (docs/mqtt.md, docs/registers.md) and `hookwatch regmap`.
"""
