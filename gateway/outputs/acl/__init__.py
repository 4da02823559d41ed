"""The broker's permissions of a site, generated from every door's topics (``hookwatch
config acl``)."""
