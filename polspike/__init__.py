"""polspike."""
