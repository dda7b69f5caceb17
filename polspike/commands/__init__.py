"""CLI command modules, one per pipeline stage; each registers on polspike.cli.app_typer."""
