"""The spatial order of a large world's rows, renewed at each full pair search, and its kernel."""
