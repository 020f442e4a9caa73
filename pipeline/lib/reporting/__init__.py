"""The report: its page, figures, the customer summary and the paper's numbers."""
