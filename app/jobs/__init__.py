"""/v1/jobs: create, list, get and cancel jobs, and read what they produce (events, metrics, evaluations,
checkpoints, the learning curve and the policy)."""
