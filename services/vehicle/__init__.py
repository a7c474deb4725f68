"""The vehicle role: one connected vehicle, a thin Zenoh adapter around mapcontainer.vehicle.VehicleAgent."""
