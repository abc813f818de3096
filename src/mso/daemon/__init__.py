"""The node daemon, assembled from options: what ``mso node`` runs on every device.

:mod:`mso.daemon.config` settles the options (flags over a config file) and checks them before
anything listens; :mod:`mso.daemon.assembly` builds the core, the transport, the routing view,
the executor and the metrics endpoint from them and runs the node until it is stopped. Kept out
of the CLI so that the daemon is one call, from a command line or from a program.
"""
