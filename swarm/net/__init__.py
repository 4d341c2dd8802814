"""Zenoh transport: sessions, the key space of a run, validated subscriptions, the stores that
deliveries land in, fault injection for tests, access control (TLS, ACL) and the processes'
pacing."""
