"""Static files the API serves (the dashboard page, ``service.routes.dashboard``)."""
