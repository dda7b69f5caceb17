"""spike_sim."""
