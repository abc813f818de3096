"""Each distributed procedure, whole in its own module or package: every role, its transition
table keyed by typed events, its deadline and its failure outcome.

- :mod:`.base` — what every procedure shares: states, one table, a deadline.
- :mod:`.deploy` — Algorithm 1: the origin, a chain head's node, a probe hop, a builder.
- :mod:`.relocation` — a move (and a restore's coordinator): coordinator, new host, producer,
  old host, a module each.
- :mod:`.restore` — a restore's participants: the surviving ends, the replacement, a crashed
  instance's restart budget.
- :mod:`.remap` — chain and global remap at their coordinator; the recovery rule.
- :mod:`.membership` — heartbeats, the detector, the failed set, reset and rejoin.
- :mod:`.status` — a status fan-out; :mod:`.instance` — a vertex instance's life at its host.

``python -m mso.protocol.procedures`` prints every table (docs/architecture.md is drawn from it).
"""
