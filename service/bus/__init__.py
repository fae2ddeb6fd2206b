"""The Zenoh layer: subscribers, publishers and queryables around the pipeline."""
