"""Services: the scheduler (curriculum and stopping rule), the REST API and the CLI."""
