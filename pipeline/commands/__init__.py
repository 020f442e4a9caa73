"""Commands run by hand, never by ./dvc.yaml (`python -m pipeline.commands.<name>`, or the
`spi-boter-<name>` script): a module or a package each. No command imports another, nor a stage."""
