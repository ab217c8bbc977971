"""The service kernel: what the API (`app`) and the workers (`worker`) share and neither owns: settings, the database
models and sessions, ids, storage paths, the job queue and the job state machine. It imports neither of them."""
