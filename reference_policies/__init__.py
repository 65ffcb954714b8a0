"""The reference policy: scripted experts, demonstrations, training and DAgger corrections of models/octo-reference-robosuite."""
