"""Speed figures of the backend's operations, kept apart from the code they time (``genre bench``)."""
