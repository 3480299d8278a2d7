"""What people look at: the terminal view, the dashboard and the report writers."""
