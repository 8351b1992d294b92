/* Start-up of a bare build on the SAM3X8E (make arm): the vector table and the reset
 * handler (copy .data, clear .bss, run main). Under the Arduino core, the core has its own. */
#include <stdint.h>

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
int main(void);
void Reset_Handler(void);
void Default_Handler(void);
void TC0_Handler(void);

#define SCB_VTOR (*(volatile uint32_t *)0xE000ED08u)

void Default_Handler(void)
{
    for (;;) { /* an unexpected fault or interrupt: the hardware watchdog resets the board */
    }
}

typedef void (*vector)(void);

/* 16 system exceptions, then the SAM3X's 45 peripheral interrupts; only TC0 (27) is used */
__attribute__((section(".vectors"), used)) static const vector vectors[16 + 45] = {
    (vector)(uintptr_t)&_estack, Reset_Handler, Default_Handler, Default_Handler, Default_Handler,
    Default_Handler, Default_Handler, 0, 0, 0, 0, Default_Handler, Default_Handler, 0, Default_Handler,
    Default_Handler,
    [16 ... 16 + 26] = Default_Handler,
    [16 + 27] = TC0_Handler,
    [16 + 28 ... 16 + 44] = Default_Handler,
};

void Reset_Handler(void)
{
    uint32_t *src = &_sidata, *dst = &_sdata;
    while (dst < &_edata)
        *dst++ = *src++;
    for (dst = &_sbss; dst < &_ebss;)
        *dst++ = 0;
    SCB_VTOR = (uint32_t)(uintptr_t)vectors;
    main();
    for (;;) {
    }
}
