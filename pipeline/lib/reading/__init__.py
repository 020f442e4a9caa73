"""Reading measurements: tracker/controller exports, the probe's orientation, campaigns,
presets, and the prepared inputs every learning stage starts from."""
