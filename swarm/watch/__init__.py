"""Pure watchers: vehicle events, localization breaches and the commands a vehicle was given."""
