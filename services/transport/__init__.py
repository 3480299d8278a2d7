"""How nodes talk: Zenoh sessions, the wire messages and their schemas, topic names, access control and MCAP files."""
