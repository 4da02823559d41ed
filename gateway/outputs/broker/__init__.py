"""The broker session under the MQTT output and the Sparkplug node: paho session engine,
broker settings, the on-disk outbox."""
