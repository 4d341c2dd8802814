"""Zenoh transport: sessions, key space, access control (TLS, ACL) and the processes' pacing."""
