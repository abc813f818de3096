"""Where the kernel's routing view will go (not built yet).

On real devices and on the netns testbed a routing daemon (babeld, OLSR, batman-adv) keeps the
kernel's routing table; the node must read it rather than be told. The plan: a ``KernelRoutes``
that is a :class:`~mso.net.routes.TableRoutes` fed by pyroute2 — a dump of the main table at
start, then ``RTM_NEWROUTE``/``RTM_DELROUTE`` events; a route whose gateway is the destination
itself, or which has no gateway, is a neighbour — mapping addresses to node ids through the
same ``--peer``-style address book, and byte counters read from the interface. It is the only
view that needs netlink, so pyroute2 stays out of every other path.
"""
