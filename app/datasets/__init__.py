"""/v1/datasets: upload (streamed, validated in a sandboxed child), list, get, delete."""
