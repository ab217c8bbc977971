"""What an owner may hold (quotas) and the lock that serialises an owner's writes that must see each other."""
