"""API routes, one module per resource; each stays thin and delegates to the job store and the uploads."""
