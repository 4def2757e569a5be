"""skinmap.wire: every layout skinmap publishes over Zenoh and logs to MCAP, defined once.

- ``skinmap.wire.messages``: the binary messages (elements, surface, strains; SKMP header) and
  the JSON status/info objects, pure encode/decode; the byte tables of docs/zenoh.md are
  rendered from ``LAYOUT_TABLES`` (``layout_table``) and checked by the tests;
- ``skinmap.wire.keys``: the key space under ``<prefix>/<device>/`` and its encodings;
- ``skinmap.wire.session``: loopback-safe Zenoh session configuration.

Needs only numpy (and eclipse-zenoh for ``session``); nothing of the gateway.
"""
