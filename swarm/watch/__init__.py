"""Pure watchers: vehicle events and localization breaches."""
