"""The CUDA back end: forward renders, recycled replays and the retrieval's engine on a GPU."""
