"""The wire's messages by procedure family; :mod:`mso.protocol.messages` puts them in one
union (``Message``) and re-exports every name, so code imports them from there."""
