"""The retrieval loop (issue 7): not implemented yet."""
