"""openpi interoperability: serve through openpi policy servers, and serve openpi clients."""
