"""``rsmb report``: the HTML report of a store and its figures."""
