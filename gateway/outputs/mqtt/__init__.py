"""The MQTT output: schema, messages, the pump and its rooms, the site's lives."""
