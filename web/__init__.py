"""Static pages the server serves (transmitter, dashboard): package data, no Python."""
