"""How the service's processes run: `drop serve`'s API-and-worker tree, and children that die with their parent."""
