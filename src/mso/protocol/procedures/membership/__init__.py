"""Membership: who is alive, suspected or failed, and how nodes come back.

- :mod:`.liveness` — neighbour liveness: heartbeats in, the silent and the unreachable out.
- :mod:`.detector` — the state machines: each peer's life, and the indirect probe's two waits
  (:class:`~.detector.Suspicion` at the node that lost a peer, :class:`~.detector.Vouch` at a
  node asked about it).
- :mod:`.status` — its part of a node's status, as typed records.
- :mod:`.peers` — the component: heartbeats, the one failed set, incarnations, reset, rejoin,
  app sync.
"""
