"""The live service: the receiver daemon, its event sources (recordings at their pace, live
cameras, the virtual event camera), what the transmitter page shows, and the publisher and
spool that carry its reports to the server."""
