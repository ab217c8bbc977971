"""What operators watch: request ids and the access log, Prometheus metrics, and the health probes."""
