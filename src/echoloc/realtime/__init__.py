"""Live data: the wire protocol, TCP/UDP transport, the stream that processes frames as
they arrive, and the live view."""
