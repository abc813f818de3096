"""Membership: who is alive, suspected or failed, and how nodes come back.

- :mod:`.liveness` — liveness of the watched nodes: heartbeats in, the silent (suspected) and
  the unreachable out; a route withdrawal never restarts the silence clock.
- :mod:`.detector` — the state machines: each peer's life, and the indirect probe's two waits
  (:class:`~.detector.Suspicion` at the node that watches a silent peer, :class:`~.detector.Vouch`
  at a node asked about it).
- :mod:`.claims` — whom to ask (k members), when another's failure claim is believed
  (corroboration, incarnation bounds), and how claims spread (piggybacked on beats).
- :mod:`.reach` — whether a node out of reach must be declared: re-placing what it runs would
  let events flow (unreachable is not failed).
- :mod:`.ranks` — after a partition heals, who resets: the tie-break, read from this node's
  view and the other's beat.
- :mod:`.status` — its part of a node's status, as typed records.
- :mod:`.sync` — app sync for a node that rejoins.
- :mod:`.peers` — the component, :class:`~.peers.Membership`: its layers below, each using
  only those beneath it:

  - :mod:`.tables` — what it holds of the others: each one's state, the one failed set,
    incarnations, and how many nodes those tables admit.
  - :mod:`.declare` — declaring a peer failed, in one place (its own word, or a claim believed).
  - :mod:`.suspicion` — the indirect probe at both ends: suspect and ask, answer or vouch.
  - :mod:`.beats` — beats out, the silent and blocking suspected on each tick, routes changed.
  - :mod:`.rejoin` — beats in: restarts, healed partitions (who resets), rejoin, ``NodeUp``.
"""
