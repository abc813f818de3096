"""The network seam: how a node reaches other nodes and what it knows of the routes.

``base`` holds the interfaces (:class:`~mso.net.base.Transport`,
:class:`~mso.net.base.RoutingView`); ``forwarding`` the one shared way of holding control
frames while routes converge; ``tcp`` and ``shaping`` the real transport; ``routes_static``,
``routes_emulator`` (and later ``routes_kernel``) the routing views. Nothing here knows about
apps: it moves opaque frames between node ids.
"""
