"""The service under load: submissions, watchers, latency per route."""
