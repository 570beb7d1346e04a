#pragma once
class TwoWire { public: void begin() {} };
extern TwoWire Wire;
