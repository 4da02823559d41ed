"""Process plumbing: the thread ↔ loop hand-over, back-off, doors, rate-limited logs, safe
writers and the bounded YAML reader, OS priority, sd_notify."""
