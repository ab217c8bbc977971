"""What every route needs: the request dependencies, bearer auth, problem+json errors, list pages, and the bounds
on what a request may hold (body size and idle time, upload and stream slots)."""
