"""The reference policy: scripted experts, demonstrations and training of models/octo-reference-robosuite."""
